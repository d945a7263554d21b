"""Task 'pick' with the R3M ResNet encoder (official checkpoint, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/pick_r3m.py:small --workdir=runs/pick_r3m
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  not yet timed (no pretraining; the cache stage runs the frozen ResNet once over every frame); each cell's
          stage times: results/small/README.md.
Results:  results/small/pick_r3m/README.md (not published yet: the grid skips the cell where the weights are absent)
Needs the official weights (README.md, "Weights of the R3M and DINO baselines"). No pretrain stage.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "r3m", variant)
