"""Task 'push' with the `ae` encoder (roboshape/encoders/ae.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/push_ae.py:small   (variants :paper, :small, :tiny)
Results:  results/small/push_ae/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "ae", variant)
