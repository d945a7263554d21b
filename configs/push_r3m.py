"""Task 'push' with the R3M ResNet encoder (official checkpoint, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/push_r3m.py:small --workdir=runs/push_r3m
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs); the other stages not yet measured.
Result: not yet measured (the official weights cannot be downloaded on the 2-core CPU machine).
Needs the official weights (README.md, "Weights of the R3M and DINO baselines"). No pretrain stage.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "r3m", variant)
