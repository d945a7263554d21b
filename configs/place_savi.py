"""Task 'place' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/place_savi.py:small --workdir=runs/place_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  about fourteen hours on one core at :small (SAVi's three pretraining seeds about two and a half hours, the
          three behaviour-cloning seeds of place's 15000 steps, three times push's, about ten and a half, the evaluation
          an hour), plus the task's collection (2000 demos, shared by its runs: results/small/report/report.md
          "Compute", column collect); measured on 2-core CPUs (results/small/README.md "Machines and speed"), each
          stage's time in results/small/place_savi/stages.json.
Results:  results/small/place_savi/README.md
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "savi", variant)
