"""Task 'push' with the `state` encoder (roboshape/encoders/state.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/push_state.py:small   (variants :paper, :small, :tiny)
Results:  results/small/push_state/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "state", variant)
