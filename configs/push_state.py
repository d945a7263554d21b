"""Control: task 'push' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/push_state.py:small --workdir=runs/push_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine (2 cores shared with two other runs): collect 110.6 s (200 + 10 episodes),
cache 3.4 s, train_policy 942.4 s (5000 steps), evaluate 425.4 s (3 seeds x 20 rollouts x 4 levels).
Result, :small (2026-11-24): success 1.00 ± 0.00 at the train level, L1 1.00 ± 0.00, L2 1.00 ± 0.00, L3 1.00 ± 0.00
(mean ± std over 3 evaluation seeds; results/small/push_state/README.md). :paper: not yet measured.
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "state", variant)
