"""Control: task 'push' with one token per object from the simulator's exact poses, an unordered set without ids.

Command:  python launch.py --config=configs/push_poses.py:small --workdir=runs/push_poses
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime:  not measured as a cell of the grid (its probes' stage times: results/small/recipe/probes.csv).
Results:  results/small/push_poses/README.md (not published yet; the pick ladder's rung: results/small/recipe)
Needs a dataset that stores observation/state. No pretraining, no rendering needed by the encoder. Token layout:
roboshape/encoders/poses.py.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "poses", variant)
