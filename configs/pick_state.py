"""Control: task 'pick' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/pick_state.py:small --workdir=runs/pick_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime, :small on the 2-core CPU machine (2 cores shared with two other runs): collect 232.6 s (200 + 10 episodes),
cache 3.1 s, train_policy 991.9 s (5000 steps), evaluate 423.2 s (3 seeds x 20 rollouts x 4 levels).
Result, :small (2026-11-24): success 0.95 ± 0.04 at the train level, L1 0.95 ± 0.04, L2 0.95 ± 0.04, L3 0.90 ± 0.07
(mean ± std over 3 evaluation seeds; results/small/pick_state/README.md). :paper: not yet measured.
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "state", variant)
