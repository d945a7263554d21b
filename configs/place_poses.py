"""Control: task 'place' with one token per object from the simulator's exact poses, an unordered set without ids.

Command:  python launch.py --config=configs/place_poses.py:small --workdir=runs/place_poses
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Results:  results/small/recipe/README.md (the pick ladder: state, absolute state, poses, objects)
Needs a dataset that stores observation/state. No pretraining, no rendering needed by the encoder. Token layout:
roboshape/encoders/poses.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "poses", variant)
