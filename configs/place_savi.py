"""Task 'place' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/place_savi.py:small --workdir=runs/place_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime: not yet measured.
Result: not yet measured.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "savi", variant)
