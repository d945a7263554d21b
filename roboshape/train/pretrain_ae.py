"""The `ae` encoder's "pretrain" stage: the frame autoencoder (roboshape/models/ae.py) trained as SAVi is, then frozen.

  python launch.py --config=configs/push_ae.py:small --workdir=runs/push_ae
  enc = load_encoder("runs/push_ae")      # a FrozenEncoder: one token [B, 1, D] per frame, D = ae.latent_size

Equal pretraining by construction: every training setting is read from `config.savi` itself, not copied into an
`ae` section: the data (clips of savi.train.clip_length frames, savi.train.batch_size a batch, batch i the same
clips as SAVi's batch i), savi.train.steps, the learning-rate schedule (warmup, cosine decay), Adam, gradient
clipping, the loss (savi.train.rgb_weight x RGB MSE + savi.train.depth_weight x depth MSE, against the frames
pooled by savi.pool), the checkpoint, log and validation cadence, and the seed. Training runs the same loop, train
step and checkpoint code as SAVi's (roboshape/train/pretrain.py: `fit`, `Compiled`). The only field of its own is
`ae.latent_size` (0: savi.slot_size).

Writes under <workdir>/ae/: checkpoints/ (orbax; resumed after a kill), tb/ (TensorBoard), val_metrics.json and
.png (reconstruction MSE, and depth MSE with a depth weight, on the first savi.eval.frames frames of
savi.eval.episodes val episodes, every savi.eval.every steps).
"""
import functools
import os
from typing import Any, Callable, Dict, Iterator, Sequence

import jax
import numpy as np

from roboshape.cli import UserError
from roboshape.models import ae
from roboshape.models import savi
from roboshape.models.encoder import FrozenEncoder
from roboshape.train import pretrain


def ae_dir(workdir: str) -> str:
  return os.path.join(workdir, "ae")


def latent_size(config) -> int:
  """D: config.ae.latent_size, or config.savi.slot_size when it is 0 or the config has no ae section."""
  return int(config.get("ae", {}).get("latent_size", 0)) or int(config.savi.slot_size)


def validate_config(config) -> None:
  """SAVi's checks (the AE shares its encoder, decoder, pool and training fields) and the AE's own."""
  pretrain.validate_config(config)
  if latent_size(config) < 1:
    raise UserError(f"ae.latent_size={latent_size(config)} must be >= 1 (0: savi.slot_size).")
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
  """The (cached) AE and its jitted train step and eval for `config` (its savi section, ae.latent_size)."""
  return _compiled_for(config.savi.to_json(sort_keys=True), latent_size(config), int(config.env.resolution))


def evaluate(comp: pretrain.Compiled, params, episodes: Sequence[Dict[str, np.ndarray]],
             frames: int) -> Dict[str, float]:
  """Reconstruction MSE over the first `frames` frames of each episode (image uint8 [S, H, W, 3], and depth uint16
  [S, H, W] mm), against the frames pooled by the model's input_pool: recon_mse, and depth_mse (metres) for a
  model that predicts depth, over the episodes that store it."""
  pool = comp.model.input_pool
  mses, depth_mses = [], []
  for episode in episodes:
    out = jax.device_get(comp.eval_video(params, episode["image"][None, :frames]))
    target = np.asarray(savi.pool_frames(pretrain.to_float(episode["image"][:frames]), pool))
    mses.append(float(np.mean((out["recon"][0] - target) ** 2)))
    if "depth" in out and "depth" in episode:
      metres = episode["depth"][:frames, :, :, None].astype(np.float32) / 1000.0
      depth_mses.append(float(np.mean((out["depth"][0] - np.asarray(savi.pool_frames(metres, pool))[..., 0]) ** 2)))
  result = {"recon_mse": float(np.mean(mses)) if mses else float("nan")}
  if depth_mses:
    result["depth_mse"] = float(np.mean(depth_mses))
  return result


def train(config, workdir: str, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
          val_episodes: Sequence[Dict[str, np.ndarray]] = ()) -> Dict[str, Any]:
  """Trains the AE to `config.savi.train.steps`, resuming from the latest checkpoint in <workdir>/ae/checkpoints.

  batches_from and the result as in roboshape.train.pretrain.train; val_episodes: dicts with image uint8
  [S, H, W, 3] (and depth uint16 [S, H, W]).
  """
  validate_config(config)
  comp, ec = compiled(config), config.savi.eval
  validation = None
  if val_episodes:
    validation = pretrain.Validation(
        run=lambda params, step: evaluate(comp, params, val_episodes[:ec.episodes], ec.frames),
        keys=("recon_mse",),
        describe=lambda r: " ".join(f"val {k.replace('_', ' ')} {v:.5f}" for k, v in r.items()))
  return pretrain.fit(config, ae_dir(workdir), comp, batches_from, validation, "AE")


def run(config, workdir: str) -> None:
  """The pretrain stage of the `ae` encoder: the AE trained on the dataset of `config` as SAVi would be."""
  result = train(config, workdir, *pretrain.data_source(config, workdir))
  if result["eval"]:
    step, metrics = result["eval"][-1]
    print(f"[pretrain] step {step}: AE val recon MSE {metrics['recon_mse']:.5f}", flush=True)


def _frozen_step(model: ae.AE, params, carry, frames):
  """FrozenEncoder step: (params, (), frames uint8 [B, H, W, 3]) -> (latents [B, 1, D], ()); no memory."""
  latents = model.apply({"params": params}, pretrain.to_float(frames), method=ae.AE.encode)
  return latents[:, None, :], carry


def load_encoder(workdir: str) -> FrozenEncoder:
  """The AE trained in `workdir` (its latest checkpoint), frozen: one token per frame, its latent [B, 1, D]."""
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  config = stages.load_config(workdir)
  comp = compiled(config)
  directory = os.path.join(ae_dir(workdir), "checkpoints")
  params, step = pretrain.restore_latest(config, workdir, comp, directory, "AE")
  return FrozenEncoder(
      name="ae", params=params, step=functools.partial(_frozen_step, comp.model),
      init_state=lambda batch_size: (), num_tokens=1, token_dim=comp.model.latent_size,
      identity=f"ae:{os.path.abspath(directory)}@{step}")

