"""Task 'place' with the `state` encoder (roboshape/encoders/state.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/place_state.py:small   (variants :paper, :small, :tiny)
Results:  results/small/place_state/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "state", variant)
