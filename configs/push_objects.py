"""Control: task 'push' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/push_objects.py[:paper|small|tiny] --workdir=runs/push_objects
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "objects", variant)
