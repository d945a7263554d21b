"""Task 'push' with the `savi` encoder (roboshape/encoders/savi.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/push_savi.py:small   (variants :paper, :small, :tiny)
Results:  results/small/push_savi/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "savi", variant)
