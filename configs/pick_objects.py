"""Control: task 'pick' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/pick_objects.py:small --workdir=runs/pick_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime, :small on the 2-core CPU machine: collect 232.6 s (200 + 10 episodes, measured with pick_state, the same
dataset, the cores shared with two other runs); cache 5.6 s, train_policy about 5200 s (5000 steps, one core, the
other busy), evaluate 954 s.
Result: :small 0.03 at the train level, L1 0.03, L2 0.05, L3 0.03 (results/small/pick_objects/); 3 of 60 grasp.
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "objects", variant)
