"""SAVi's evaluator: FG-ARI and matched mIoU of the slot masks on whole validation episodes, and the
decomposition figure (roboshape/eval/decomposition.py has the metrics).

  decompose = functools.partial(savi.decompose, model)
  metrics = evaluate(decompose, params, episodes, frames=6, background_ids=(0, 1), pool=model.input_pool)
  validation = validation(config, root, model, episodes)   # what the pretrain stage runs (config.pretrain.eval,
                                                           # config.savi.eval)

  python -m roboshape.eval.slots WORKDIR    # whether the run's SAVi finds the cube, by the cube's size in the frame
"""
import argparse
import functools
import os
import sys
from typing import Callable, Dict, Optional, Sequence, Union

import jax
import numpy as np

from roboshape import errors
from roboshape import rundir
from roboshape.envs import ids
from roboshape.eval import decomposition
from roboshape.models import savi
from roboshape.train import pretrain

# The task objects whose masks a slot should find on its own, by name: their segmentation ids.
OBJECTS = {"cube": ids.CUBE, "goal": ids.GOAL, "hand": ids.HAND}
# (params, video uint8 [B, T, H, W, 3], the first frame's ids [B, H, W] with the robot as one, read by a conditional
# SAVi) -> dict(masks [B, T, K, h, w], recon [B, T, h, w, 3], rgb [B, T, K, h, w, 3])
Decompose = Callable[[object, np.ndarray, np.ndarray], Dict[str, np.ndarray]]


def evaluate(decompose: Decompose, params, episodes: Sequence[Dict[str, np.ndarray]], frames: int,
             background_ids: Sequence[int] = (0, 1), pool: int = 1,
             figure_path: Union[str, Sequence[str], None] = None, figure_frames: int = 4,
             title: str = "", views: Sequence[str] = ()) -> Dict[str, float]:
  """FG-ARI and matched mIoU of the slot masks on whole (first `frames` frames of) episodes, the segmentation ids
  `background_ids` left out.

  fg_ari scores each video as one clustering, so a slot that changes object between frames counts against it (the
  bar); fg_ari_frames is the mean over frames of each frame's own FG-ARI, the decomposition without that consistency.
  Per task object (OBJECTS: the cube, the target or bin, the hand), <name>_iou is the best IoU of any one slot's mask
  with the object's mask, averaged over the frames that show it, which FG-ARI (dominated by the large masks) hides;
  cube_found is the share of those frames in which one slot covers the cube with IoU >= decomposition.FOUND_IOU.

  Masks of a pooled model (savi.pool = `pool`) are compared at the segmentation's resolution, each mask pixel
  repeated pool x pool; the reconstruction error is against the pooled frames.

  episodes: dicts with image uint8 [S, H, W, 3] and segmentation uint8 [S, H, W]. Writes the decomposition figure
  of the first episode's first `figure_frames` frames to `figure_path` when given (a sequence of paths: the figure
  of the i-th episode to the i-th path, e.g. each camera's view of one episode). With `views` (camera names, two
  or more) the episodes are each episode's views in that order, one after the other, and every metric is also
  given per view as <metric>_<view>, over that view's episodes alone.
  """
  paths = [figure_path] if isinstance(figure_path, str) else list(figure_path or ())
  scored = []   # per episode: (fg_ari, its frames' FG-ARIs, mIoU, recon MSE, {object: best IoU per frame})
  for i, episode in enumerate(episodes):
    video = episode["image"][:frames]
    out, masks = _decomposed(decompose, params, episode, frames, pool)
    seg = ids.robot_as_one(episode["segmentation"][:frames])   # the robot is one object
    best = {name: decomposition.best_slot_iou(episode["segmentation"][:frames], masks, object_id)
            for name, object_id in OBJECTS.items()}                     # the hand apart from the arm
    pooled = np.asarray(savi.pool_frames(video.astype(np.float32) / 255.0, pool))
    scored.append((decomposition.fg_ari(seg, masks, background_ids),
                   [decomposition.fg_ari(seg[t:t + 1], masks[t:t + 1], background_ids) for t in range(len(seg))],
                   decomposition.matched_miou(seg, masks, background_ids),
                   float(np.mean((out["recon"][0] - pooled) ** 2)), best))
    if i < len(paths):
      n = figure_frames
      decomposition.decomposition_figure(pooled[:n], out["recon"][0, :n], out["rgb"][0, :n], out["masks"][0, :n],
                                         paths[i], _with_cube(title, best["cube"][:n]))
  metrics = _summary(scored)
  if len(views) > 1:
    for v, view in enumerate(views):
      metrics.update({f"{key}_{view}": value for key, value in _summary(scored[v::len(views)]).items()})
  return metrics


def _decomposed(decompose: Decompose, params, episode: Dict[str, np.ndarray], frames: int, pool: int):
  """(the model's outputs on an episode's first `frames` frames, its masks [T, K, H, W] at the segmentation's
  resolution)."""
  out = jax.device_get(decompose(params, episode["image"][None, :frames],
                                 ids.robot_as_one(episode["segmentation"][:1])))
  return out, decomposition.upsample_masks(out["masks"][0], pool)


def _summary(scored) -> Dict[str, float]:
  """`evaluate`'s metrics over some of its episodes' scores."""
  best = {name: np.concatenate([s[4][name] for s in scored]) if scored else np.zeros(0) for name in OBJECTS}
  seen = {name: v[~np.isnan(v)] for name, v in best.items()}
  aris, ious, mses = [s[0] for s in scored], [s[2] for s in scored], [s[3] for s in scored]
  frame_aris = [a for s in scored for a in s[1]]
  with np.errstate(all="ignore"):
    objects = {f"{name}_iou": float(v.mean()) if v.size else float("nan") for name, v in seen.items()}
    objects["cube_found"] = (float(np.mean(seen["cube"] >= decomposition.FOUND_IOU)) if seen["cube"].size
                             else float("nan"))
    return {**objects, "fg_ari": float(np.nanmean(aris)) if aris else float("nan"),
            "fg_ari_frames": float(np.nanmean(frame_aris)) if frame_aris else float("nan"),
            "miou": float(np.nanmean(ious)) if ious else float("nan"),
            "recon_mse": float(np.mean(mses)) if mses else float("nan")}


def _with_cube(title: str, cube_iou: np.ndarray) -> str:
  """The figure's title with its frames' best cube IoU (or that the cube is not in view)."""
  seen = cube_iou[~np.isnan(cube_iou)]
  said = (f"cube: best slot IoU {seen.mean():.2f} (found in {int(np.sum(seen >= decomposition.FOUND_IOU))} of "
          f"{seen.size} frames)" if seen.size else "cube not in view")
  return f"{title}; {said}" if title else said


def validation(config, root: str, model: savi.SAVi, episodes: Sequence[Dict[str, np.ndarray]]) -> pretrain.Validation:
  """SAVi's validation during pretraining: `evaluate` on the first pretrain.eval.episodes of `episodes` (their
  first pretrain.eval.frames frames), scored and drawn as config.savi.eval says, with the decomposition figure of
  each evaluation in <root>/figures/step_<step>.png. With several env.cameras `episodes` holds each episode in
  every view, one after the other (roboshape/train/pretrain.py data_source): all of them are scored, and the first
  episode's other views are drawn in step_<step>_<camera>.png; the metrics are also given per view (`evaluate`'s
  `views`) and the printed line names each view's cube IoU and share found."""
  ec, own = config.pretrain.eval, config.savi.eval
  decompose = functools.partial(savi.decompose, model)
  cameras = tuple(config.env.cameras)

  def figure(step):
    return [os.path.join(root, rundir.FIGURES_DIR, f"step_{step:07d}" + (f"_{c}" if v else "") + ".png")
            for v, c in enumerate(cameras)]

  return pretrain.Validation(
      run=lambda params, step: evaluate(decompose, params, episodes[:ec.episodes * len(cameras)], ec.frames,
                                        own.background_ids,
                                        model.input_pool, figure(step),
                                        own.figure_frames, f"{config.name} step {step}", cameras),
      keys=("fg_ari", "fg_ari_frames", "miou", "cube_iou", "cube_found"), ylim=(None, 1.0),
      describe=lambda r: (f"val FG-ARI {r['fg_ari']:.3f} (per frame {r['fg_ari_frames']:.3f}) mIoU "
                          f"{r['miou']:.3f} cube IoU {r['cube_iou']:.3f} (found in {r['cube_found']:.0%} of frames) "
                          f"recon MSE {r['recon_mse']:.5f}"
                          + "".join(f"; {c}: FG-ARI {r[f'fg_ari_{c}']:.3f} cube IoU {r[f'cube_iou_{c}']:.3f} "
                                    f"found {r[f'cube_found_{c}']:.0%}" for c in cameras if len(cameras) > 1)))


def cube_by_area(workdir: str) -> Dict[str, list]:
  """{camera: decomposition.found_by_area of the cube} for the SAVi trained in `workdir`, on the frames its
  pretraining validates (pretrain.data_source: the first pretrain.eval.frames frames of pretrain.eval.episodes val
  episodes), each camera view of them apart: whether a slot finds the cube, by how much of the frame it fills."""
  from roboshape.encoders import savi as savi_encoder  # pylint: disable=import-outside-toplevel
  config = rundir.load_config(workdir)
  model, params, _ = savi_encoder.load(workdir, config)
  _, episodes = pretrain.data_source(config, workdir)
  cameras, frames = tuple(config.env.cameras), config.pretrain.eval.frames
  decompose = functools.partial(savi.decompose, model)
  found = {}
  for v, camera in enumerate(cameras):
    segmentations, masks = [], []
    for episode in episodes[v::len(cameras)]:
      masks.append(_decomposed(decompose, params, episode, frames, model.input_pool)[1])
      segmentations.append(episode["segmentation"][:frames])
    found[camera] = decomposition.found_by_area(np.concatenate(segmentations), np.concatenate(masks), ids.CUBE)
  return found


def area_table(found: Dict[str, list]) -> str:
  """`cube_by_area`'s result as a markdown table, a row per camera and bin of the cube's share of the frame."""
  lines = ["| view | the cube's share of the frame | frames | best slot's IoU | found (IoU >= "
           f"{decomposition.FOUND_IOU}) |", "| --- | --- | --- | --- | --- |"]
  for camera, rows in found.items():
    lines += [f"| {camera} | {r['lo']:.1%} - {r['hi']:.1%} | {r['frames']} | {r['iou']:.2f} | {r['found']:.0%} |"
              for r in rows if r["frames"]]
  return "\n".join(lines)


def main(argv) -> int:
  parser = argparse.ArgumentParser(description="Whether the SAVi trained in a workdir finds the cube, by the cube's "
                                               "share of the frame, on its validation frames, per camera view.")
  parser.add_argument("workdir")
  args = parser.parse_args(argv)
  try:
    print(area_table(cube_by_area(args.workdir)))
  except errors.UserError as e:
    return errors.print_error(e)
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
