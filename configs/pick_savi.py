"""Task 'pick' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/pick_savi.py:small --workdir=runs/pick_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime, :small on the 2-core CPU machine: collect 232.6 s (200 + 10 episodes, measured with pick_state, the same
dataset, the cores shared with two other runs); pretrain 2930 s (8000 steps), cache 12 s, train_policy 3730 s,
evaluate 947 s (one core each, the other busy with another run).
Result: :small 0.03 at every level (results/small/pick_savi/); SAVi FG-ARI 0.553, mIoU 0.231 at step 8000, and no
slot holds the cube.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "savi", variant)
