"""Control: task 'push' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, read from config.savi; frozen, one token per frame).

Command:  python launch.py --config=configs/push_ae.py:small --workdir=runs/push_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs); the other stages not yet measured.
Result: not yet measured.
Its pretrain stage is roboshape/train/pretrain_ae.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "ae", variant)
