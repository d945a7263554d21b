"""Task 'place' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/place_savi.py:small --workdir=runs/place_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime: :small on one core of the 2-core CPU (the other busy): pretrain about 60 min (8000 steps, resumed once),
         cache 23 s, train_policy 3827 s, evaluate 1265 s.
Result: :small 0.00 at every level, 1 of 240 rollouts grasps (results/small/place_savi/); FG-ARI 0.286, no slot
        follows the cube. :paper: not yet measured.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "savi", variant)
