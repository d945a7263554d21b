"""Control: task 'place' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/place_objects.py:small --workdir=runs/place_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime: :small on one core of the 2-core CPU (the other busy): cache 6.0 s, train_policy 4345 s, evaluate 1304 s.
Result: :small 0.00 at every level (results/small/place_objects/); 14 of 60 grasp, 4 lift, none over the bin.
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "objects", variant)
