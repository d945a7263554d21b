"""Task 'push' with the SAVi (pretrained on the task's own demos, frozen) encoder and the transformer BC policy.

Command:  python launch.py --config=configs/push_savi.py[:paper|small|tiny] --workdir=runs/push_savi
Runtime and expected result: see the table in README.md (filled from measured runs).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "savi", variant)
