"""Control: task 'place' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/place_objects.py:small --workdir=runs/place_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  about nine hours on one core at :small (three training seeds of place's 15000 steps, about two and a half
          hours each, mostly behaviour cloning on a token per object, and the evaluation, about 50 minutes), plus the
          task's collection (2000 demos, shared by its runs: results/small/report/report.md "Compute", column collect);
          measured on 2-core CPUs (results/small/README.md "Machines and speed"), each stage's time in
          results/small/place_objects/stages.json.
Results:  results/small/place_objects/README.md
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "objects", variant)
