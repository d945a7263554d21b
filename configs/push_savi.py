"""Task 'push' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/push_savi.py:small --workdir=runs/push_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs); pretrain about 0.5 s per step alone (1847 s to step 3500 of its
8000, results/savi_small/README.md); cache, train_policy and evaluate not yet measured.
Result: SAVi alone, :small, validation FG-ARI 0.611 at step 2500 (0.5995 at step 3500; results/savi_small/); policy
success: not yet measured, at any variant.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "savi", variant)
