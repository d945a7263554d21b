"""Control: task 'push' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/push_objects.py:small --workdir=runs/push_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs), cache 4.5 s, train_policy 5651.2 s (5000 steps, the cores shared
with 2-3 other runs; about 0.6 s per step alone), evaluate 378.1 s.
Result, :small (2026-11-24), with the old segmentation (the whole robot one id, before the hand got its own id in
roboshape-envs-5): success 0.52 ± 0.02 at the train level, L1 0.40 ± 0.04, L2 0.53 ± 0.08, L3 0.53 ± 0.06
(results/small/push_objects/README.md). With the hand's id, and at :paper: not yet measured.
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "objects", variant)
