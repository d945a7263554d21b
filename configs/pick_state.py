"""Control: task 'pick' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/pick_state.py:small --workdir=runs/pick_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  under half an hour per training seed on one core at :small, plus the task's collection (2000 demos: about 45
          minutes on one core, shared by its runs); each cell's stage times: results/small/README.md.
Results:  results/small/pick_state/README.md
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "state", variant)
