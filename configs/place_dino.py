"""Task 'place' with the `dino` encoder (roboshape/encoders/baselines.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/place_dino.py:small   (variants :paper, :small, :tiny)
Results:  results/small/place_dino/README.md (not published yet)
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "dino", variant)
