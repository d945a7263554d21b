"""The `ae` encoder's "pretrain" stage: the frame autoencoder (roboshape/models/ae.py) trained as SAVi is, then frozen.

  python launch.py --config=configs/push_ae.py:small --workdir=runs/push_ae
  enc = roboshape.load_encoder("runs/push_ae")   # served by roboshape/encoders/ae.py: one token [B, 1, D] a frame

Equal pretraining by construction: every training setting is read from `config.savi` itself, not copied into an
`ae` section: the data (clips of savi.train.clip_length frames, savi.train.batch_size a batch, batch i the same
clips as SAVi's batch i), savi.train.steps, the learning-rate schedule (warmup, cosine decay), Adam, gradient
clipping, the loss (RGB MSE + savi.train.depth_weight x depth MSE, against the frames pooled by savi.pool), the
checkpoint, log and validation cadence, and the seed. Training runs the same loop, train step and checkpoint code
as SAVi's (roboshape/train/pretrain.py: `fit`, `Compiled`). The only field of its own is
`ae.latent_size` (0: savi.slot_size).

Writes under <workdir>/ae/: checkpoints/ (orbax; resumed after a kill), tb/ (TensorBoard), val_metrics.json and
.png (what the stage wiring's evaluator measures: roboshape/eval/reconstruction.py, the reconstruction MSE, and
depth MSE with a depth weight, on the first savi.eval.frames frames of savi.eval.episodes val episodes, every
savi.eval.every steps).

Seeds as SAVi's (roboshape/train/pretrain.py, `train_seeds`): savi.train.seeds = (s1, s2, ...) trains one AE per
seed in <workdir>/ae/seed_<s>/ and selects the one with the lowest final validation reconstruction MSE (ties: the
lower seed), recorded in <workdir>/ae/selected.json, with every seed's curve in <workdir>/ae/seeds_recon_mse.png.
"""
import functools
from typing import Any, Callable, Dict, Iterator, Optional, Sequence

import numpy as np

from roboshape import rundir
from roboshape.errors import UserError
from roboshape.models import ae
from roboshape.models import savi
from roboshape.train import pretrain


def validate_config(config) -> None:
  """SAVi's checks (the AE shares its encoder, decoder, pool and training fields) and the AE's own."""
  pretrain.validate_config(config)
  if ae.latent_size(config) < 1:
    raise UserError(f"ae.latent_size={ae.latent_size(config)} must be >= 1 (0: savi.slot_size).")
  c = config.savi
  side = ae.feature_side(config.env.resolution, savi.input_pool(c), c.encoder.strides)
  grid = savi.decoder_grid_size(c, config.env.resolution)
  if side > grid and side % grid:
    raise UserError(f"the AE pools its {side}x{side} encoder features to the decoder's {grid}x{grid} grid, which "
                    "needs a multiple of it: change savi.encoder.strides or savi.decoder.strides.")


@functools.lru_cache(maxsize=8)
def _compiled_for(savi_json: str, size: int, resolution: int) -> pretrain.Compiled:
  c = pretrain.config_from_json(savi_json)
  return pretrain.Compiled(ae.build_model(c, size, resolution), c)


def compiled(config) -> pretrain.Compiled:
  """The (cached) AE and its jitted train step for `config` (its savi section, ae.latent_size)."""
  return _compiled_for(pretrain.model_json(config), ae.latent_size(config), int(config.env.resolution))


def train(config, workdir: str, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
          val_episodes: Sequence[Dict[str, np.ndarray]] = (),
          make_validation: Optional[pretrain.MakeValidation] = None, root: Optional[str] = None) -> Dict[str, Any]:
  """Trains the AE to `config.savi.train.steps`, resuming from the latest checkpoint in <root>/checkpoints (root:
  <workdir>/ae when None).

  batches_from, make_validation and the result as in roboshape.train.pretrain.train (e.g.
  roboshape.eval.reconstruction.validation); val_episodes: dicts with image uint8 [S, H, W, 3] (and depth uint16
  [S, H, W]).
  """
  validate_config(config)
  comp, root = compiled(config), root or rundir.ae_dir(workdir)
  validation = None
  if val_episodes and make_validation is not None:
    validation = make_validation(config, root, comp.model, val_episodes)
  return pretrain.fit(config, root, comp, batches_from, validation, "AE")


AE_SELECTION = pretrain.Selection("recon_mse", False, "reconstruction MSE")


def train_seeds(config, workdir: str, source: pretrain.Source,
                make_validation: Optional[pretrain.MakeValidation] = None) -> Dict[str, Any]:
  """The AE once per seed of savi.train.seeds, as roboshape.train.pretrain.train_seeds, the lowest final
  validation reconstruction MSE selected (one run in <workdir>/ae/ for seeds = ())."""
  def train_one(seed_config, root):
    return train(seed_config, workdir, *source(seed_config), make_validation=make_validation, root=root)
  return pretrain.seeds_loop(config, rundir.ae_dir(workdir), train_one, AE_SELECTION, "AE")


def run(config, workdir: str, make_validation: Optional[pretrain.MakeValidation] = None) -> None:
  """The pretrain stage of the `ae` encoder: the AE trained on the dataset of `config` as SAVi would be (once per
  seed of savi.train.seeds), validated by `make_validation` (roboshape/stages.py passes the encoder's evaluator)."""
  train_seeds(config, workdir, lambda seed_config: pretrain.data_source(seed_config, workdir), make_validation)
