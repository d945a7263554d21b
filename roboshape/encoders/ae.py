"""`ae`: a holistic frame autoencoder pretrained on the task's frames exactly as SAVi is, then frozen (one token per
frame): the in-domain baseline that holds pretraining equal and takes the objects away (roboshape/models/ae.py,
trained by roboshape/train/pretrain.py). Served here from its checkpoint's params (no optimizer state is read).

The ranges of the ae section are declared here (RANGES) and checked by `check`, with its fit to the frames.
"""
import functools
import os

from roboshape.encoders import registry
from roboshape import ranges
from roboshape import rundir
from roboshape.encoders import savi as savi_encoder
from roboshape.errors import UserError

RANGES = (ranges.Int("ae.latent_size", 0, "the AE's token width; 0: savi.slot_size"),) + savi_encoder.frame_ranges("ae")


def check(config) -> None:
  """Raises UserError for the first bad field of the ae section: RANGES, a token width >= 1, then its fit to the
  frames (roboshape.models.ae.check_config)."""
  from roboshape.models import ae  # pylint: disable=import-outside-toplevel
  ranges.check(config, RANGES)
  if ae.latent_size(config) < 1:
    raise UserError(f"ae.latent_size={ae.latent_size(config)} must be >= 1 (0: savi.slot_size).")
  ae.check_config(config.ae, int(config.env.resolution))


def load_encoder(workdir: str, config=None):
  """The AE trained in `workdir` (its newest checkpoint that restores), or in the workdir its
  pretrain.from_workdir names (savi_encoder.pretrained_source), frozen: one token per frame, its latent [B, 1, D];
  `config`: the workdir's config.json when None."""
  # pylint: disable=import-outside-toplevel
  from roboshape.models import ae
  from roboshape.models.encoder import FrozenEncoder
  workdir, config = savi_encoder.pretrained_source(config or rundir.load_config(workdir), workdir)
  model = ae.model_from_config(config)
  params, step, directory = savi_encoder.restore(config, workdir, model, rundir.pretrain_dir(workdir, "ae"), "AE")
  return FrozenEncoder(
      name="ae", params=params, step=functools.partial(ae.frozen_step, model), init_state=lambda batch_size: (),
      num_tokens=1, token_dim=model.latent_size, identity=f"ae:{os.path.abspath(directory)}@{step}")


def _build(config, workdir: str):
  del config          # the workdir's own config.json: the one its checkpoints were trained with
  return load_encoder(workdir)


def _model(config):
  from roboshape.models import ae  # pylint: disable=import-outside-toplevel
  return ae.model_from_config(config)


def _tokens(config) -> str:
  from roboshape.models import ae  # pylint: disable=import-outside-toplevel
  return f"1 x {ae.latent_size(config)}"


registry.register(registry.Kind(
    name="ae", inputs=("image",), pretrain="loop", build=_build, title="AE",
    description="a frame autoencoder with SAVi's CNN and decoder, pretrained like SAVi on the task's frames "
                "(one latent per frame; control: in-domain pretraining without objects)",
    evaluator="reconstruction",
    model=registry.PretrainModel(build=_model, selection=registry.Selection("recon_mse", False,
                                                                             "reconstruction MSE")),
    sections=("pretrain", "ae", "savi.slot_size"), check=check, order=2, tokens=_tokens, views=True))
