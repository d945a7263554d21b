"""Where a trained SAVi loses FG-ARI: per frame, per episode, without memory, per slot.

  JAX_PLATFORMS=cpu .venv/bin/python scripts/savi_diagnose.py WORKDIR [MERGE ...] [--figure PNG] [--data PATH]
  e.g. ... scripts/savi_diagnose.py runs/push_savi 2:6 8:6 2:6,8:6 --figure argmax.png   (about 3 min, 2-core CPU)

Reads WORKDIR's config and latest SAVi checkpoint (the frozen encoder the policy would use), and the validation
episodes the stage evaluates on (pretrain.eval.episodes x pretrain.eval.frames of the workdir's dataset, or of
--data), with the robot counted as one object as the stage scores it, and prints:
  1. the ground truth's share of foreground pixels per segmentation id, and the FG-ARI of three made-up
     segmentations (all objects in one cluster; the robot cut into a left and a right half; its pixels in the top
     3/16 of the image cut off);
  2. the model's video FG-ARI (the stage's `fg_ari`), its FG-ARI frame by frame, the video FG-ARI per episode with
     its table's colour, and the robot's pixels per slot on frames 0 and 12 of the first episode;
  3. the same model without memory: every frame starts from the learned first-frame slots;
  4. the video FG-ARI with slots relabelled (MERGE "a:b,c:d" counts slot a as b and c as d), and with every robot
     pixel given to the slot that holds most of them (the ceiling of fixing the robot alone).
With --figure PNG it also draws some validation episodes (--figure-episodes, default 5,6,0) at six frames: a row of
frames, a row of segmentations, a row of each pixel's most likely slot.
"""
import argparse
import os
import sys

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# pylint: disable=wrong-import-position
import jax

from roboshape import encoders
from roboshape import rundir
from roboshape.data import reader
from roboshape.data import validate
from roboshape.envs import ids
from roboshape.eval import decomposition
from roboshape.models import savi


def one_hot(labels, k):
  return np.moveaxis(np.eye(k)[labels], -1, 1)                       # [T, H, W] -> [T, K, H, W]


def merged(labels, pairs):
  """labels with each slot a of the (a, b) pairs counted as slot b (a copy)."""
  labels = labels.copy()
  for a, b in pairs:
    labels[labels == a] = b
  return labels


def draw(path, episodes, labels, rows, frames):
  """Frames, segmentations and argmax slot labels of some episodes, three rows per episode, into PNG `path`."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  from matplotlib import pyplot as plt  # pylint: disable=import-outside-toplevel
  palette = plt.get_cmap("tab10")
  fig, axes = plt.subplots(3 * len(rows), len(frames), figsize=(1.6 * len(frames), 4.8 * len(rows)), dpi=80,
                           squeeze=False)
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


def main(args):
  config = rundir.load_config(args.workdir)
  data = validate.find_dataset(args.data or rundir.data_root(config, args.workdir))
  n, length = args.episodes or config.pretrain.eval.episodes, args.frames or config.pretrain.eval.frames
  background = tuple(config.savi.eval.background_ids)
  fg_ari = lambda seg, masks: decomposition.fg_ari(seg, masks, background)
  episodes = []
  for e in reader.read_episodes(data, "val"):
    episodes.append({"image": e["image"][:length], "segmentation": ids.robot_as_one(e["segmentation"][:length])})
    if len(episodes) == n:
      break
  segs = [e["segmentation"] for e in episodes]
  k_fake = ids.NUM_IDS + 1                                            # one spare id for a cut-off piece
  ids_present, counts = np.unique(np.concatenate([s[~np.isin(s, background)] for s in segs]), return_counts=True)
  print(f"{len(episodes)} validation episodes x {length} frames of {data}")
  print("1. foreground share per id:", dict(zip(ids_present.tolist(), np.round(counts / counts.sum(), 3).tolist())))
  h, w = segs[0].shape[1:]
  cols, rows = np.arange(w)[None, None, :], np.arange(h)[None, :, None]
  robot = ids.ROBOT
  for name, fake in (("objects in one cluster", lambda s: np.where(s > robot, robot + 1, s)),
                     ("robot cut in halves", lambda s: np.where((s == robot) & (cols < w // 2), ids.NUM_IDS, s)),
                     ("robot's top 3/16 cut off", lambda s: np.where((s == robot) & (rows < 3 * h // 16),
                                                                     ids.NUM_IDS, s))):
    score = np.mean([fg_ari(s, one_hot(fake(s), k_fake)) for s in segs])
    print(f"   made-up segmentation, {name}: FG-ARI {score:.3f}")

  model = savi.model_from_config(config)
  params = encoders.build_encoder(config, args.workdir).params          # the latest SAVi checkpoint
  k, pool = model.num_slots, model.input_pool
  labels, videos, frames = [], [], []
  for e in episodes:
    out = jax.device_get(savi.decompose(model, params, e["image"][None]))
    masks = decomposition.upsample_masks(out["masks"][0], pool)
    labels.append(masks.argmax(axis=1))
    videos.append(fg_ari(e["segmentation"], masks))
    frames.append([fg_ari(e["segmentation"][t:t + 1], masks[t:t + 1]) for t in range(length)])
  tables = ["black" if e["image"][e["segmentation"] == ids.TABLE].mean() < 128 else "white" for e in episodes]
  if args.figure:
    shown = [i for i in args.figure_episodes if i < len(episodes)]
    draw(args.figure, episodes, labels, shown, sorted({0, 4, 8, 12, 16, length - 1} & set(range(length))))
  print(f"2. video FG-ARI {np.mean(videos):.3f}, per frame {np.mean(frames):.3f}; by frame:",
        np.round(np.mean(frames, axis=0), 2).tolist())
  print("   video FG-ARI per episode (table colour):",
        ", ".join(f"{i}: {v:.3f} ({t})" for i, (v, t) in enumerate(zip(videos, tables))))
  for t in (0, 12):
    if t < length:
      robot_pixels = labels[0][t][segs[0][t] == robot]
      print(f"   episode 0, frame {t}: robot pixels per slot", np.bincount(robot_pixels, minlength=k).tolist())

  init = savi.initial_slots(model, params, 1)
  step = jax.jit(lambda frame: model.apply({"params": params}, frame, init, method=savi.SAVi.step)[0])
  decode = jax.jit(lambda slots: model.apply({"params": params}, slots, method=savi.SAVi.decode)["masks"])
  videos, frames = [], []
  for e in episodes:
    masks = np.concatenate([np.asarray(decode(step(f[None]))) for f in e["image"].astype(np.float32) / 255.0])
    masks = decomposition.upsample_masks(masks, pool)
    videos.append(fg_ari(e["segmentation"], masks))
    frames.append([fg_ari(e["segmentation"][t:t + 1], masks[t:t + 1]) for t in range(length)])
  print(f"3. without memory: video FG-ARI {np.mean(videos):.3f}, per frame {np.mean(frames):.3f}; by frame:",
        np.round(np.mean(frames, axis=0), 2).tolist())

  def relabelled(relabel):
    return np.mean([fg_ari(seg, one_hot(relabel(seg, lab), k)) for seg, lab in zip(segs, labels)])
  print("4. relabelled slots:")
  for merge in args.merges:
    pairs = [tuple(int(x) for x in item.split(":")) for item in merge.split(",")]
    print(f"   {merge}: video FG-ARI {relabelled(lambda seg, lab, p=pairs: merged(lab, p)):.3f}")
  def whole(seg, lab):
    if not (seg == robot).any():
      return lab
    return np.where(seg == robot, np.bincount(lab[seg == robot], minlength=k).argmax(), lab)
  print(f"   every robot pixel in the robot's main slot: video FG-ARI {relabelled(whole):.3f}")


if __name__ == "__main__":
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("workdir", help="a run's workdir with SAVi checkpoints (the pretrain stage's)")
  parser.add_argument("merges", nargs="*", help='slot relabellings "a:b,c:d" (slot a counted as b, c as d)')
  parser.add_argument("--data", default="", help="the dataset (default: the workdir config's data.dir, or "
                                                  "<workdir>/data)")
  parser.add_argument("--episodes", type=int, default=0, help="validation episodes (default: pretrain.eval.episodes)")
  parser.add_argument("--frames", type=int, default=0, help="first frames per episode (default: pretrain.eval.frames)")
  parser.add_argument("--figure", help="also draw frames, segmentations and argmax slots into this PNG")
  parser.add_argument("--figure-episodes", type=lambda s: [int(x) for x in s.split(",")], default=[5, 6, 0],
                      help="comma-separated validation episodes the figure shows (default 5,6,0)")
  main(parser.parse_args())
