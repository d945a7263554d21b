"""Task 'push' with the `r3m` encoder (roboshape/encoders/baselines.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/push_r3m.py:small   (variants :paper, :small, :tiny)
Results:  results/small/push_r3m/README.md (not published yet)
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "r3m", variant)
