"""Task 'push' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/push_savi.py:small --workdir=runs/push_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs); pretrain about 0.5 s per step alone (1847 s to step 3500 of its
8000, results/savi_small/README.md); with another run on the other core: pretrain 3361 s (8000 steps), cache
12.7 s, train_policy 4284 s, evaluate 1010 s.
Result: :small 0.13 at the train level, L1 0.10, L2 0.07, L3 0.07 (results/small/push_savi/); FG-ARI 0.537 at step
8000 (0.611 at step 2500 in an earlier run, results/savi_small/), and no slot holds the cube.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "savi", variant)
