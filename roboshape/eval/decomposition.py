"""How well slot masks separate the objects of a scene: FG-ARI, matched mIoU, and the decomposition figure.

Both metrics compare one video at a time: the true segmentation ids [T, H, W] against the slot masks
[T, K, H, W], pooled over all frames, so a slot that swaps objects between frames is penalised (slot identity
must hold over time). Pixels whose true id is in `background_ids` are ignored: by default roboshape's backdrop
(id 0) and the table (id 1), the two static surfaces behind every scene, so the scores measure how the robot, the
cube, the target or bin and the distractors are separated rather than how the large table is split off.

  fg_ari(segmentation, masks, background_ids=(0, 1)) -> float in [-1, 1] (nan when < 2 foreground pixels)
  matched_miou(segmentation, masks, background_ids=(0, 1)) -> float in [0, 1] (nan when no foreground object)
"""
from typing import Optional, Sequence

import numpy as np
from scipy import optimize

from roboshape import fileio


def _pairs(n: np.ndarray) -> np.ndarray:
  n = n.astype(np.float64)
  return n * (n - 1.0) / 2.0


def adjusted_rand_index(true_ids: np.ndarray, pred_ids: np.ndarray) -> float:
  """ARI of two labelings of the same items (any integer labels, any shapes of equal size); nan if < 2 items."""
  true_ids = np.asarray(true_ids).ravel()
  pred_ids = np.asarray(pred_ids).ravel()
  if true_ids.size != pred_ids.size:
    raise ValueError(f"labelings differ in size: {true_ids.size} vs {pred_ids.size}")
  if true_ids.size < 2:
    return float("nan")
  _, t = np.unique(true_ids, return_inverse=True)
  _, p = np.unique(pred_ids, return_inverse=True)
  table = np.zeros((t.max() + 1, p.max() + 1), np.int64)
  np.add.at(table, (t, p), 1)
  index = _pairs(table).sum()
  rows = _pairs(table.sum(axis=1)).sum()
  cols = _pairs(table.sum(axis=0)).sum()
  expected = rows * cols / _pairs(np.array(true_ids.size))
  maximum = 0.5 * (rows + cols)
  if maximum == expected:  # both labelings trivial (one cluster, or all singletons): they agree
    return 1.0
  return float((index - expected) / (maximum - expected))


def _foreground(segmentation: np.ndarray, background_ids: Sequence[int]) -> np.ndarray:
  return ~np.isin(segmentation, np.asarray(background_ids, dtype=segmentation.dtype))


def fg_ari(segmentation: np.ndarray, masks: np.ndarray, background_ids: Sequence[int] = (0, 1)) -> float:
  """Foreground ARI of one video: segmentation int [T, H, W], soft or hard masks [T, K, H, W] (argmax over K)."""
  segmentation = np.asarray(segmentation)
  pred = np.argmax(np.asarray(masks), axis=-3)                       # [T, H, W]
  if pred.shape != segmentation.shape:
    raise ValueError(f"masks {masks.shape} do not match segmentation {segmentation.shape}")
  keep = _foreground(segmentation, background_ids)
  return adjusted_rand_index(segmentation[keep], pred[keep])


def matched_miou(segmentation: np.ndarray, masks: np.ndarray, background_ids: Sequence[int] = (0, 1)) -> float:
  """Mean IoU of the foreground objects of one video, each matched to its own slot by the Hungarian algorithm.

  segmentation int [T, H, W]; masks [T, K, H, W] (argmax over K gives each pixel's slot). Each true object
  (foreground id present in the video) is matched to a distinct slot maximising the total IoU over the whole
  video volume (all pixels, background included, so a slot that spills over the table loses IoU); objects left
  without a slot (more objects than slots) score 0. Returns the mean over the true objects.
  """
  segmentation = np.asarray(segmentation)
  masks = np.asarray(masks)
  num_slots = masks.shape[-3]
  pred = np.argmax(masks, axis=-3).ravel()
  seg = segmentation.ravel()
  ids = np.unique(seg[_foreground(seg, background_ids)])
  if ids.size == 0:
    return float("nan")
  true_onehot = seg[None, :] == ids[:, None]                              # [G, P]
  pred_onehot = pred[None, :] == np.arange(num_slots)[:, None]           # [K, P]
  inter = true_onehot.astype(np.float64) @ pred_onehot.T.astype(np.float64)  # [G, K]
  union = true_onehot.sum(1)[:, None] + pred_onehot.sum(1)[None, :] - inter
  iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
  rows, cols = optimize.linear_sum_assignment(iou, maximize=True)
  return float(iou[rows, cols].sum() / ids.size)


def best_slot_iou(segmentation: np.ndarray, masks: np.ndarray, object_id: int) -> np.ndarray:
  """Per frame, the best IoU of any one slot's mask with object `object_id`'s mask: float [T], NaN in the frames
  where the object is not in view. segmentation int [T, H, W]; masks [T, K, H, W] (argmax over K gives each pixel's
  slot). A small object that no slot holds on its own scores its share of the slot that swallows it."""
  segmentation = np.asarray(segmentation)
  masks = np.asarray(masks)
  num_slots = masks.shape[-3]
  pred = np.argmax(masks, axis=-3)                                          # [T, H, W]
  truth = (segmentation == object_id).reshape(len(segmentation), -1)        # [T, P]
  slots = pred.reshape(len(pred), 1, -1) == np.arange(num_slots)[None, :, None]   # [T, K, P]
  inter = (slots & truth[:, None]).sum(-1)
  union = (slots | truth[:, None]).sum(-1)
  best = (inter / np.maximum(union, 1)).max(-1)
  return np.where(truth.any(-1), best, np.nan)


FOUND_IOU = 0.5     # a slot with at least this IoU with an object's mask has found it
# The bins of an object's share of the frame's pixels that found_by_area reports (at 64x64: 20, 41, 82, 205 pixels).
AREA_EDGES = (0.0, 0.005, 0.01, 0.02, 0.05, 1.0)


def found_by_area(segmentation: np.ndarray, masks: np.ndarray, object_id: int,
                  edges: Sequence[float] = AREA_EDGES) -> list:
  """Whether a slot finds an object, by the object's size in the frame: for each bin [lo, hi) of the share of the
  frame's pixels that are the object's (the last bin includes hi), a dict of lo, hi, the frames in the bin, their
  mean best-slot IoU (best_slot_iou) and the share of them found (IoU >= FOUND_IOU), NaN for an empty bin. Frames
  without the object are left out. segmentation int [T, H, W]; masks [T, K, H, W]."""
  segmentation = np.asarray(segmentation)
  iou = best_slot_iou(segmentation, masks, object_id)
  area = (segmentation == object_id).reshape(len(segmentation), -1).mean(-1)
  rows = []
  for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
    upper = area <= hi if i == len(edges) - 2 else area < hi
    picked = iou[~np.isnan(iou) & (area >= lo) & upper]
    rows.append(dict(lo=lo, hi=hi, frames=int(picked.size),
                     iou=float(picked.mean()) if picked.size else float("nan"),
                     found=float(np.mean(picked >= FOUND_IOU)) if picked.size else float("nan")))
  return rows


def upsample_masks(masks: np.ndarray, factor: int) -> np.ndarray:
  """Nearest-neighbour upsampling of masks [..., h, w] by an integer factor -> [..., h * factor, w * factor] (the
  masks of a model of pooled frames, at the segmentation's resolution)."""
  return np.asarray(masks).repeat(factor, axis=-2).repeat(factor, axis=-1)


def masked_slots(rgb: np.ndarray, masks: np.ndarray, fill: float = 1.0) -> np.ndarray:
  """Each slot's reconstruction shown through its mask: rgb [..., K, H, W, 3], masks [..., K, H, W] -> same as rgb,
  blended towards `fill` (white) where the slot does not own the pixel."""
  m = np.asarray(masks)[..., None]
  return np.clip(m * np.asarray(rgb) + (1.0 - m) * fill, 0.0, 1.0)


def decomposition_figure(frames: np.ndarray, recon: np.ndarray, rgb: np.ndarray, masks: np.ndarray,
                         path: str, title: Optional[str] = None) -> str:
  """Saves a grid as PNG: a row per frame with the input, the reconstruction and every slot's masked reconstruction.

  frames [T, H, W, 3] (uint8, or float in [0, 1]), recon [T, H, W, 3] float, rgb [T, K, H, W, 3] float,
  masks [T, K, H, W]. Returns `path`.
  """
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  from matplotlib import pyplot as plt  # pylint: disable=import-outside-toplevel

  frames = np.asarray(frames)
  if frames.dtype == np.uint8:
    frames = frames.astype(np.float32) / 255.0
  slots = masked_slots(rgb, masks)
  num_frames, num_slots = slots.shape[:2]
  cols = 2 + num_slots
  fig, axes = plt.subplots(num_frames, cols, figsize=(1.2 * cols, 1.25 * num_frames + (0.3 if title else 0)),
                           squeeze=False)
  for t in range(num_frames):
    panels = [frames[t], np.clip(recon[t], 0, 1)] + [slots[t, k] for k in range(num_slots)]
    for c, image in enumerate(panels):
      ax = axes[t, c]
      ax.imshow(image, interpolation="nearest")
      ax.set_xticks([])
      ax.set_yticks([])
      if t == 0:
        ax.set_title("input" if c == 0 else "recon" if c == 1 else f"slot {c - 2}", fontsize=7)
    axes[t, 0].set_ylabel(f"t={t}", fontsize=7)
  if title:
    fig.suptitle(title, fontsize=8)
  return fileio.save_figure(fig, path, dpi=100)
