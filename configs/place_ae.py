"""Control: task 'place' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, read from config.savi; frozen, one token per frame).

Command:  python launch.py --config=configs/place_ae.py:small --workdir=runs/place_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/place)
Runtime: :small on one core of the 2-core CPU (the other busy): pretrain 637 s (8000 steps), cache 11.8 s,
         train_policy 734 s, evaluate 1159 s.
Result: :small 0.00 at every level, no rollout grasps (results/small/place_ae/); reconstruction MSE 0.0196.
Its pretrain stage is roboshape/train/pretrain_ae.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("place", "ae", variant)
