"""Control: task 'place' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, from the shared pretrain section; frozen, one token per
frame).

Command:  python launch.py --config=configs/place_ae.py:small --workdir=runs/place_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime:  about three and a half hours on one core at :small (the AE's three pretraining seeds about 40 minutes, the
          three behaviour-cloning seeds of place's 15000 steps, three times push's, about two hours, the evaluation an
          hour), plus the task's collection (2000 demos, shared by its runs: results/small/report/report.md "Compute",
          column collect); measured on 2-core CPUs (results/small/README.md "Machines and speed"), each stage's time in
          results/small/place_ae/stages.json.
Results:  results/small/place_ae/README.md
Run with the place control setting (configs/common.py TASK_CONTROL), as every encoder on place.
Its pretrain stage is roboshape/train/pretrain.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "ae", variant)
