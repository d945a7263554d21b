"""Task 'pick' with the `objects` encoder (roboshape/encoders/objects.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/pick_objects.py:small   (variants :paper, :small, :tiny)
Results:  results/small/pick_objects/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "objects", variant)
