"""Task 'place' with the `poses` encoder (roboshape/encoders/poses.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/place_poses.py:small   (variants :paper, :small, :tiny)
Results:  results/small/place_poses/README.md (not published yet)
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "poses", variant)
