"""Task 'push' with the SAVi encoder (pretrained on the task's own demos, frozen) and the transformer BC policy.

Command:  python launch.py --config=configs/push_savi.py:small --workdir=runs/push_savi
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime:  about four and a half hours on one core at :small (SAVi's three pretraining seeds about an hour and a half,
          the three behaviour-cloning seeds about two and a quarter hours, the evaluation about 40 minutes), plus the
          task's collection (2000 demos, shared by its runs: results/small/report/report.md "Compute", column collect);
          measured on 2-core CPUs (results/small/README.md "Machines and speed"), each stage's time in
          results/small/push_savi/stages.json.
Results:  results/small/push_savi/README.md
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "savi", variant)
