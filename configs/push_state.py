"""Control: task 'push' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/push_state.py[:paper|small|tiny] --workdir=runs/push_state
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining,
no rendering needed by the encoder. Runtime and measured result: results/small/push_state/README.md.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "state", variant)
