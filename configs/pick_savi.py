"""Task 'pick' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/pick_savi.py:small --workdir=runs/pick_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime, :small on the 2-core CPU machine: collect 232.6 s (200 + 10 episodes, measured with pick_state, the same
dataset, the cores shared with two other runs); the other stages not yet measured.
Result: not yet measured.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "savi", variant)
