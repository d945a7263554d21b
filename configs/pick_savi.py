"""Task 'pick' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/pick_savi.py:small --workdir=runs/pick_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  about six to seven hours on one core at :small (SAVi's three pretraining seeds about two and a half hours, the
          three behaviour-cloning seeds three and a half, the evaluation under an hour), plus the task's collection
          (2000 demos: about 45 minutes on one core, shared by its runs); each cell's stage times:
          results/small/README.md.
Results:  results/small/pick_savi/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "savi", variant)
