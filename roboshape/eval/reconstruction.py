"""The AE's evaluator: reconstruction MSE (and depth MSE) of a frame autoencoder on validation episodes.

  metrics = evaluate(model, params, episodes, frames=config.pretrain.eval.frames)
  validation = validation(config, root, model, episodes)   # what the pretrain stage runs every pretrain.eval.every
                                                           # steps
"""
import functools
from typing import Dict, Sequence

import jax
import numpy as np

from roboshape.models import savi
from roboshape.train import pretrain


@functools.partial(jax.jit, static_argnums=0)
def _reconstruct(model, params, video):
  return model.apply({"params": params}, savi.to_float(video))


def evaluate(model, params, episodes: Sequence[Dict[str, np.ndarray]], frames: int) -> Dict[str, float]:
  """Reconstruction MSE over the first `frames` frames of each episode (image uint8 [S, H, W, 3], and depth uint16
  [S, H, W] mm), against the frames pooled by the model's input_pool: recon_mse, and depth_mse (metres) for a
  model that predicts depth, over the episodes that store it."""
  pool = model.input_pool
  mses, depth_mses = [], []
  for episode in episodes:
    out = jax.device_get(_reconstruct(model, params, episode["image"][None, :frames]))
    target = np.asarray(savi.pool_frames(savi.to_float(episode["image"][:frames]), pool))
    mses.append(float(np.mean((out["recon"][0] - target) ** 2)))
    if "depth" in out and "depth" in episode:
      metres = episode["depth"][:frames, :, :, None].astype(np.float32) / 1000.0
      depth_mses.append(float(np.mean((out["depth"][0] - np.asarray(savi.pool_frames(metres, pool))[..., 0]) ** 2)))
  result = {"recon_mse": float(np.mean(mses)) if mses else float("nan")}
  if depth_mses:
    result["depth_mse"] = float(np.mean(depth_mses))
  return result


def validation(config, root: str, model, episodes: Sequence[Dict[str, np.ndarray]]) -> pretrain.Validation:
  """The AE's validation during pretraining: `evaluate` on the first pretrain.eval.episodes of `episodes` (each in
  every view of env.cameras, roboshape/train/pretrain.py data_source)."""
  del root
  ec = config.pretrain.eval
  return pretrain.Validation(
      run=lambda params, step: evaluate(model, params, episodes[:ec.episodes * len(config.env.cameras)], ec.frames),
      keys=("recon_mse",),
      describe=lambda r: " ".join(f"val {k.replace('_', ' ')} {v:.5f}" for k, v in r.items()))
