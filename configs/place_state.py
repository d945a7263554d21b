"""Control: task 'place' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/place_state.py:small --workdir=runs/place_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime: :small on one core of the 2-core CPU: collect 707 s (shared with all place runs), train_policy 681 s,
         evaluate 330 s (no rendering but the recorded rollouts).
Result: :small 0.10 at the train level (L1 0.10, L2 0.10, L3 0.05); 54 of 60 grasp, 30 lift, 6 place in the bin
        (results/small/place_state/). Run with the place control setting (configs/common.py TASK_CONTROL).
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "state", variant)
