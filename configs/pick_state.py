"""Control: task 'pick' with the privileged simulator state as the encoder (one token per step), the upper bound.

Command:  python launch.py --config=configs/pick_state.py:small --workdir=runs/pick_state
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  about half an hour on one core at :small (three training seeds of about 8 minutes each and the evaluation,
          about 6 minutes), plus the task's collection (2000 demos, shared by its runs: results/small/report/report.md
          "Compute", column collect); measured on 2-core CPUs (results/small/README.md "Machines and speed"), each
          stage's time in results/small/pick_state/stages.json.
Results:  results/small/pick_state/README.md
Needs a dataset that stores observation/state (every dataset collected since roboshape-envs-2). No pretraining, no
rendering needed by the encoder.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "state", variant)
