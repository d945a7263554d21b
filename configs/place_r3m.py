"""Task 'place' with the `r3m` encoder (roboshape/encoders/baselines.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/place_r3m.py:small   (variants :paper, :small, :tiny)
Results:  results/small/place_r3m/README.md (not published yet)
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "r3m", variant)
