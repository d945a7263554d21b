"""Control: task 'pick' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, from the shared pretrain section; frozen, one token per
frame).

Command:  python launch.py --config=configs/pick_ae.py:small --workdir=runs/pick_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime:  about two hours on one core at :small (the AE's three pretraining seeds and the three behaviour-cloning seeds
          about half an hour each, the evaluation three quarters of an hour), plus the task's collection (2000 demos:
          about 45 minutes on one core, shared by its runs); each cell's stage times: results/small/README.md.
Results:  results/small/pick_ae/README.md
Its pretrain stage is roboshape/train/pretrain.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "ae", variant)
