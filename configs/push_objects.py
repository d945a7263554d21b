"""Control: task 'push' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/push_objects.py:small --workdir=runs/push_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime:  about three hours on one core at :small (three training seeds of about 50 minutes each, mostly behaviour
          cloning on a token per object, and the evaluation, about 25 minutes), plus the task's collection (2000 demos,
          shared by its runs: results/small/report/report.md "Compute", column collect); measured on 2-core CPUs
          (results/small/README.md "Machines and speed"), each stage's time in results/small/push_objects/stages.json.
Results:  results/small/push_objects/README.md
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "objects", variant)
