"""Control: task 'place' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/place_state.py:small --workdir=runs/place_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  about an hour and a half on one core at :small (three training seeds of place's 15000 steps, about 25 minutes
          each, and the evaluation, about 10 minutes), plus the task's collection (2000 demos, shared by its runs:
          results/small/report/report.md "Compute", column collect); measured on 2-core CPUs (results/small/README.md
          "Machines and speed"), each stage's time in results/small/place_state/stages.json.
Results:  results/small/place_state/README.md
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "state", variant)
