"""Control: task 'push' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, from the shared pretrain section; frozen, one token per
frame).

Command:  python launch.py --config=configs/push_ae.py:small --workdir=runs/push_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime:  about an hour and a half on one core at :small (the AE's three pretraining seeds about 20 minutes, the three
          behaviour-cloning seeds about 25, the evaluation about 45), plus the task's collection (2000 demos, shared by
          its runs: results/small/report/report.md "Compute", column collect); measured on 2-core CPUs
          (results/small/README.md "Machines and speed"), each stage's time in results/small/push_ae/stages.json.
Results:  results/small/push_ae/README.md
Its pretrain stage is roboshape/train/pretrain.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "ae", variant)
