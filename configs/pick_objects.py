"""Control: task 'pick' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/pick_objects.py:small --workdir=runs/pick_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  one to two hours per training seed on one core at :small (mostly behaviour cloning on a token per object),
          plus the task's collection (2000 demos: about 45 minutes on one core, shared by its runs); each cell's stage
          times: results/small/README.md.
Results:  results/small/pick_objects/README.md
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "objects", variant)
