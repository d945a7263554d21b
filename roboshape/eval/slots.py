"""SAVi's evaluator: FG-ARI and matched mIoU of the slot masks on whole validation episodes, and the
decomposition figure (roboshape/eval/decomposition.py has the metrics).

  decompose = functools.partial(savi.decompose, model)
  metrics = evaluate(decompose, params, episodes, config.savi.eval, pool=model.input_pool)
  validation = validation(config, root, model, episodes)   # what the pretrain stage runs every savi.eval.every steps
"""
import functools
import os
from typing import Callable, Dict, Optional, Sequence

import jax
import numpy as np

from roboshape.envs import ids
from roboshape.eval import decomposition
from roboshape.models import savi
from roboshape.train import pretrain

# (params, video uint8 [B, T, H, W, 3]) -> dict(masks [B, T, K, h, w], recon [B, T, h, w, 3], rgb [B, T, K, h, w, 3])
Decompose = Callable[[object, np.ndarray], Dict[str, np.ndarray]]


def evaluate(decompose: Decompose, params, episodes: Sequence[Dict[str, np.ndarray]], eval_config, pool: int = 1,
             figure_path: Optional[str] = None, title: str = "") -> Dict[str, float]:
  """FG-ARI and matched mIoU of the slot masks on whole (first `eval_config.frames` frames of) episodes.

  fg_ari scores each video as one clustering, so a slot that changes object between frames counts against it (the
  bar); fg_ari_frames is the mean over frames of each frame's own FG-ARI, the decomposition without that consistency.

  Masks of a pooled model (savi.pool = `pool`) are compared at the segmentation's resolution, each mask pixel
  repeated pool x pool; the reconstruction error is against the pooled frames.

  episodes: dicts with image uint8 [S, H, W, 3] and segmentation uint8 [S, H, W]. Writes the decomposition figure
  of the first episode to `figure_path` when given.
  """
  aris, frame_aris, ious, mses = [], [], [], []
  for i, episode in enumerate(episodes):
    video = episode["image"][:eval_config.frames]
    out = jax.device_get(decompose(params, video[None]))
    seg = ids.robot_as_one(episode["segmentation"][:eval_config.frames])   # the robot is one object
    masks = decomposition.upsample_masks(out["masks"][0], pool)         # at the segmentation's resolution
    aris.append(decomposition.fg_ari(seg, masks, eval_config.background_ids))
    frame_aris.extend(decomposition.fg_ari(seg[t:t + 1], masks[t:t + 1], eval_config.background_ids)
                      for t in range(len(seg)))
    ious.append(decomposition.matched_miou(seg, masks, eval_config.background_ids))
    frames = np.asarray(savi.pool_frames(video.astype(np.float32) / 255.0, pool))
    mses.append(float(np.mean((out["recon"][0] - frames) ** 2)))
    if i == 0 and figure_path:
      n = eval_config.figure_frames
      decomposition.decomposition_figure(frames[:n], out["recon"][0, :n], out["rgb"][0, :n], out["masks"][0, :n],
                                         figure_path, title)
  with np.errstate(all="ignore"):
    return {"fg_ari": float(np.nanmean(aris)) if aris else float("nan"),
            "fg_ari_frames": float(np.nanmean(frame_aris)) if frame_aris else float("nan"),
            "miou": float(np.nanmean(ious)) if ious else float("nan"),
            "recon_mse": float(np.mean(mses)) if mses else float("nan")}


def validation(config, root: str, model: savi.SAVi, episodes: Sequence[Dict[str, np.ndarray]]) -> pretrain.Validation:
  """SAVi's validation during pretraining: `evaluate` on the first config.savi.eval.episodes of `episodes`, with
  the decomposition figure of each evaluation in <root>/figures/step_<step>.png."""
  ec = config.savi.eval
  decompose = functools.partial(savi.decompose, model)
  return pretrain.Validation(
      run=lambda params, step: evaluate(decompose, params, episodes[:ec.episodes], ec, model.input_pool,
                                        os.path.join(root, "figures", f"step_{step:07d}.png"),
                                        f"{config.name} step {step}"),
      keys=("fg_ari", "fg_ari_frames", "miou"), ylim=(None, 1.0),
      describe=lambda r: (f"val FG-ARI {r['fg_ari']:.3f} (per frame {r['fg_ari_frames']:.3f}) mIoU "
                          f"{r['miou']:.3f} recon MSE {r['recon_mse']:.5f}"))
