"""Task 'pick' with the R3M ResNet (official checkpoint, frozen) encoder and the transformer BC policy.

Command:  python launch.py --config=configs/pick_r3m.py[:paper|small|tiny] --workdir=runs/pick_r3m
Runtime and expected result: see the table in README.md (filled from measured runs).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "r3m", variant)
