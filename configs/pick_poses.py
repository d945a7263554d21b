"""Task 'pick' with the `poses` encoder (roboshape/encoders/poses.py), the rest as configs/common.py sets it.

Command:  python launch.py --config=configs/pick_poses.py:small   (variants :paper, :small, :tiny)
Results:  results/small/pick_poses/README.md (not published yet)
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "poses", variant)
