"""Control: task 'push' with the AE encoder (a frame autoencoder pretrained on the task's own demos exactly as SAVi
is: the same frames, steps, batches, schedule and loss, read from config.savi; frozen, one token per frame).

Command:  python launch.py --config=configs/push_ae.py:small --workdir=runs/push_ae
          (variants :paper, :small, :tiny; the task's dataset can be shared: --config.data.dir=runs/data/push)
Runtime, :small on the 2-core CPU machine: collect 110.6 s (200 + 10 episodes, measured with push_state, the same
dataset, the cores shared with two other runs); pretrain 697 s (8000 steps), cache 6.7 s, train_policy 1036 s,
evaluate 1005 s (one core each, the other busy with another run).
Result: :small 0.05 at the train level, L1 0.02, L2 0.02, L3 0.00 (results/small/push_ae/); reconstruction MSE
0.0212 at step 8000 (SAVi's 0.0130).
Its pretrain stage is roboshape/train/pretrain_ae.py; ae.latent_size sets the token width (0: savi.slot_size).
"""
from configs import common


def get_config(variant: str = "paper"):
  return common.get_config("push", "ae", variant)
