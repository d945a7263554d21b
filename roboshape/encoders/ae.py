"""`ae`: a holistic frame autoencoder pretrained on the task's frames exactly as SAVi is, then frozen (one token per
frame): the in-domain baseline that holds pretraining equal and takes the objects away (roboshape/models/ae.py,
roboshape/train/pretrain_ae.py). Served here from its checkpoint's params (no optimizer state is read)."""
import functools
import os

from roboshape import encoders
from roboshape import rundir
from roboshape.encoders import savi as savi_encoder


def load_encoder(workdir: str, config=None):
  """The AE trained in `workdir` (its newest checkpoint that restores), frozen: one token per frame, its latent
  [B, 1, D]; `config`: the workdir's config.json when None."""
  # pylint: disable=import-outside-toplevel
  from roboshape.models import ae
  from roboshape.models.encoder import FrozenEncoder
  config = config or rundir.load_config(workdir)
  model = ae.build_model(config.savi, ae.latent_size(config), int(config.env.resolution))
  params, step, directory = savi_encoder.restore(config, workdir, model, rundir.ae_dir(workdir), "AE")
  return FrozenEncoder(
      name="ae", params=params, step=functools.partial(ae.frozen_step, model), init_state=lambda batch_size: (),
      num_tokens=1, token_dim=model.latent_size, identity=f"ae:{os.path.abspath(directory)}@{step}")


def _build(config, workdir: str):
  del config          # the workdir's own config.json: the one its checkpoints were trained with
  return load_encoder(workdir)


encoders.register(encoders.Kind(
    name="ae", inputs=("image",), pretrain="roboshape.train.pretrain_ae", build=_build, title="AE",
    description="a frame autoencoder with SAVi's CNN and decoder, pretrained like SAVi on the task's frames "
                "(one latent per frame; control: in-domain pretraining without objects)",
    evaluator="roboshape.eval.reconstruction"))
