"""Task 'place' with the DINO ViT encoder (official checkpoint, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/place_dino.py:small --workdir=runs/place_dino
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  not yet timed (no pretraining; the cache stage runs the frozen ViT once over every frame); each cell's stage
          times: results/small/README.md.
Results:  results/small/place_dino/README.md (not published yet: the grid skips the cell where the weights are absent)
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
Needs the official weights (README.md, "Weights of the R3M and DINO baselines"). No pretrain stage.
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "dino", variant)
