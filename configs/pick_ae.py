"""Control: task 'pick' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, read from config.savi; frozen, one token per frame).

Command:  python launch.py --config=configs/pick_ae.py:small --workdir=runs/pick_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/pick)
Runtime, :small on the 2-core CPU machine: collect 232.6 s (200 + 10 episodes, measured with pick_state, the same
dataset, the cores shared with two other runs); pretrain ~610 s of training (8000 steps), cache 7.7 s,
train_policy 716 s, evaluate ~800 s (one core each, the other busy with another run).
Result: :small 0.00 at every level (results/small/pick_ae/); reconstruction MSE 0.0161 at step 8000.
Its pretrain stage is roboshape/train/pretrain_ae.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("pick", "ae", variant)
