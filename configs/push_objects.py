"""Task 'push' with the `objects` encoder (roboshape/encoders/objects.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/push_objects.py:small   (variants :paper, :small, :tiny)
Results:  results/small/push_objects/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "objects", variant)
