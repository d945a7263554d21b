"""Where a trained SAVi loses FG-ARI on the `:small` push validation set: per frame, without memory, per slot.

  JAX_PLATFORMS=cpu .venv/bin/python results/savi_small/diagnose.py WORKDIR [MERGE ...] [--figure PNG]
  e.g. ... diagnose.py runs/savi_small_v7 2:6 8:6 2:6,8:6      (about 3 min on the 2-core CPU)

Reads WORKDIR's latest SAVi checkpoint and the first 8 validation episodes x 24 frames of
runs/reproduce_small/data/push (the pretrain stage's evaluation), and prints:
  1. the ground truth's share of foreground pixels per segmentation id, and the FG-ARI of three made-up
     segmentations (all objects in one cluster; the robot cut in two halves; its pixels in the top 12 rows cut off);
  2. the model's video FG-ARI (the bar), its per-frame FG-ARI frame by frame, the video FG-ARI per episode with
     its table's colour, and the robot's pixels per slot on frames 0 and 12 of the first episode;
  3. the same model without memory: every frame starts from the learned first-frame slots;
  4. the video FG-ARI with slots relabelled (MERGE "a:b,c:d" counts slot a as b and c as d), and with every robot
     pixel given to the slot that holds most of them (the ceiling of fixing the robot alone).
With --figure PNG it also draws validation episodes 5, 6 and 0 (a black table, then a white one) at frames 0, 4, 8,
12, 16 and 23: a row of frames, a row of segmentations, a row of each pixel's most likely slot.
"""
import argparse
import os
import sys

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
# pylint: disable=wrong-import-position
import jax

from roboshape import stages
from roboshape.data import reader
from roboshape.eval import decomposition
from roboshape.models import savi
from roboshape.train import pretrain

DATA = "runs/reproduce_small/data/push/roboshape_push/1.0.0"
ROBOT = 2          # the robot's segmentation id; 0 and 1 (backdrop, table) are not scored


def restore(workdir):
  """The compiled model of WORKDIR's config and its latest SAVi parameters."""
  return pretrain.compiled(stages.load_config(workdir)), pretrain.load_encoder(workdir).params


def one_hot(labels, k):
  return np.moveaxis(np.eye(k)[labels], -1, 1)                       # [T, H, W] -> [T, K, H, W]


def video_and_frames(seg, masks):
  return (decomposition.fg_ari(seg, masks),
          [decomposition.fg_ari(seg[t:t + 1], masks[t:t + 1]) for t in range(len(seg))])


def merged(labels, pairs):
  """labels with each slot a of the (a, b) pairs counted as slot b (a copy)."""
  labels = labels.copy()
  for a, b in pairs:
    labels[labels == a] = b
  return labels


def relabelled_fg_ari(segs, labels, k, relabel):
  """Mean video FG-ARI of the argmax labels after relabel(seg, labels) -> new labels, over the episodes."""
  return np.mean([decomposition.fg_ari(seg, one_hot(relabel(seg, lab), k)) for seg, lab in zip(segs, labels)])


def draw(path, episodes, labels, rows=(5, 6, 0), frames=(0, 4, 8, 12, 16, 23)):
  """Frames, segmentations and argmax slot labels of some episodes, three rows per episode, into PNG `path`."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  from matplotlib import pyplot as plt  # pylint: disable=import-outside-toplevel
  palette = plt.get_cmap("tab10")
  fig, axes = plt.subplots(3 * len(rows), len(frames), figsize=(1.6 * len(frames), 4.8 * len(rows)), dpi=80)
  for r, i in enumerate(rows):
    for c, t in enumerate(frames):
      axes[3 * r, c].imshow(episodes[i]["image"][t])
      axes[3 * r + 1, c].imshow(palette(episodes[i]["segmentation"][t] % 10))
      axes[3 * r + 2, c].imshow(palette(labels[i][t] % 10))
      axes[3 * r, c].set_title(f"episode {i}, t={t}", fontsize=7)
  for ax in axes.flat:
    ax.axis("off")
  fig.tight_layout()
  fig.savefig(path)
  print("figure:", path)


def main(workdir, merges, figure=None):
  episodes = [{k: e[k][:24] for k in ("image", "segmentation")} for e in reader.read_episodes(DATA, "val")][:8]
  segs = [e["segmentation"] for e in episodes]
  ids, counts = np.unique(np.concatenate([s[s > 1] for s in segs]), return_counts=True)
  print("1. foreground share per id:", dict(zip(ids.tolist(), np.round(counts / counts.sum(), 3).tolist())))
  cols, rows = np.arange(64)[None, None, :], np.arange(64)[None, :, None]
  for name, fake in (("objects in one cluster", lambda s: np.where(s > ROBOT, ROBOT + 1, s)),
                     ("robot cut in halves", lambda s: np.where((s == ROBOT) & (cols < 32), 15, s)),
                     ("robot cut at row 12", lambda s: np.where((s == ROBOT) & (rows < 12), 15, s))):
    print(f"   made-up segmentation, {name}: FG-ARI {np.mean([decomposition.fg_ari(s, one_hot(fake(s), 16)) for s in segs]):.3f}")

  comp, params = restore(workdir)
  k, pool = comp.model.num_slots, comp.model.input_pool
  labels, videos, frames = [], [], []
  for e in episodes:
    out = jax.device_get(comp.eval_video(params, e["image"][None]))
    masks = decomposition.upsample_masks(out["masks"][0], pool)
    labels.append(masks.argmax(axis=1))
    video, per_frame = video_and_frames(e["segmentation"], masks)
    videos.append(video)
    frames.append(per_frame)
  tables = ["black" if e["image"][e["segmentation"] == 1].mean() < 128 else "white" for e in episodes]
  if figure:
    draw(figure, episodes, labels)
  print(f"2. video FG-ARI {np.mean(videos):.3f}, per frame {np.mean(frames):.3f}; by frame:",
        np.round(np.mean(frames, axis=0), 2).tolist())
  print("   video FG-ARI per episode (table colour):",
        ", ".join(f"{i}: {v:.3f} ({t})" for i, (v, t) in enumerate(zip(videos, tables))))
  for t in (0, 12):
    print(f"   episode 0, frame {t}: robot pixels per slot", np.bincount(labels[0][t][segs[0][t] == ROBOT], minlength=k))

  init = comp.initial_slots(params, 1)
  step = jax.jit(lambda frame: comp.model.apply({"params": params}, frame, init, first=True, method=savi.SAVi.step)[0])
  decode = jax.jit(lambda slots: comp.model.apply({"params": params}, slots, method=savi.SAVi.decode)["masks"])
  videos, frames = [], []
  for e in episodes:
    float_frames = e["image"].astype(np.float32) / 255.0
    masks = np.concatenate([np.asarray(decode(step(f[None]))) for f in float_frames])
    video, per_frame = video_and_frames(e["segmentation"], decomposition.upsample_masks(masks, pool))
    videos.append(video)
    frames.append(per_frame)
  print(f"3. without memory: video FG-ARI {np.mean(videos):.3f}, per frame {np.mean(frames):.3f}; by frame:",
        np.round(np.mean(frames, axis=0), 2).tolist())

  print("4. relabelled slots:")
  for merge in merges:
    pairs = [tuple(int(x) for x in item.split(":")) for item in merge.split(",")]
    print(f"   {merge}: video FG-ARI {relabelled_fg_ari(segs, labels, k, lambda seg, lab: merged(lab, pairs)):.3f}")
  whole = lambda seg, lab: np.where(seg == ROBOT, np.bincount(lab[seg == ROBOT], minlength=k).argmax(), lab)
  print(f"   every robot pixel in the robot's main slot: video FG-ARI {relabelled_fg_ari(segs, labels, k, whole):.3f}")


if __name__ == "__main__":
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir", help="a SAVi workdir with checkpoints, e.g. runs/savi_small_v7")
  parser.add_argument("merges", nargs="*", help='slot relabellings "a:b,c:d" (slot a counted as b, c as d)')
  parser.add_argument("--figure", help="also draw frames, segmentations and argmax slots into this PNG")
  args = parser.parse_args()
  main(args.workdir, args.merges, args.figure)
