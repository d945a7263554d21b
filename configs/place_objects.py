"""Control: task 'place' with ground-truth object tokens (one per segmentation id) as the encoder, SAVi's upper bound.

Command:  python launch.py --config=configs/place_objects.py:small --workdir=runs/place_objects
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  one to two hours per training seed on one core at :small (mostly behaviour cloning on a token per object);
          on place three times the steps (15000), plus the task's collection (2000 demos: about 45 minutes on one
          core, shared by its runs); each cell's stage times: results/small/README.md.
Results:  results/small/place_objects/README.md (not published yet: the `:small` grid publishes it)
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
Reads observation/image and observation/segmentation (every dataset stores them), and observation/depth too where
env.depth is set (the :small). No pretraining. Token layout: roboshape/encoders/objects.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "objects", variant)
