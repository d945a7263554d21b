"""A quick SAVi training probe on the :small push set: trains the :small SAVi with config overrides from random
clips held in memory, prints validation FG-ARI as it goes, then where the decomposition stands per frame.

  JAX_PLATFORMS=cpu .venv/bin/python results/savi_small/probe.py STEPS [savi.FIELD=VALUE ...]
  e.g. ... probe.py 4000 savi.train.clip_length=1 savi.train.batch_size=16     (about 22 min alone on 2 cores)

Same model, optimizer and jitted train step as the pretrain stage (roboshape/train/pretrain.py); it differs in
what it leaves out (no checkpoints, TensorBoard or figures) and in its validation: the first 6 validation episodes
x 12 frames every EVERY steps (env, default 500), against 8 x 24 frames in the stage. It reads
runs/reproduce_small/data/push (results/push_small/README.md says how to make it) and caches it in /tmp.
Printed at the end: FG-ARI of the decoder's masks (the stage's metric) over all frames and on frame 0 alone, of
the last slot-attention iteration's attention maps on frame 0, and the spread of the slots over frames.
"""
import os
import sys
import time

import numpy as np

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
# pylint: disable=wrong-import-position
import jax

from configs import common
from roboshape.eval import decomposition
from roboshape.train import pretrain

DATA = "runs/reproduce_small/data/push/roboshape_push/1.0.0"
CACHE = "/tmp/roboshape_push_small_probe.npz"


def load():
  if not os.path.exists(CACHE):
    from roboshape.data import reader  # pylint: disable=import-outside-toplevel
    train, val = list(reader.read_episodes(DATA, "train")), list(reader.read_episodes(DATA, "val"))
    np.savez(CACHE, image=np.concatenate([e["image"] for e in train]), lengths=[len(e["image"]) for e in train],
             val_image=np.stack([e["image"][:24] for e in val]), val_seg=np.stack([e["segmentation"][:24] for e in val]))
  d = np.load(CACHE)
  return d["image"], d["lengths"], d["val_image"], d["val_seg"]


def save(prefix, params, frames, labels, seg):
  """Writes PREFIX.msgpack (the params) and PREFIX.png: frames, argmax slot masks and segmentation, a row each."""
  import flax.serialization  # pylint: disable=import-outside-toplevel
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  with open(prefix + ".msgpack", "wb") as f:
    f.write(flax.serialization.to_bytes(jax.device_get(params)))
  palette = np.random.default_rng(0).integers(0, 256, (32, 3), dtype=np.uint8)
  rows = [np.concatenate(list(frames), axis=1), np.concatenate(list(palette[labels]), axis=1),
          np.concatenate(list(palette[16 + seg]), axis=1)]
  imageio.imwrite(prefix + ".png", np.kron(np.concatenate(rows, axis=0), np.ones((3, 3, 1), np.uint8)))


def main(steps, overrides):
  image, lengths, val_image, val_seg = load()
  config = common.get_config("push", "savi", "small")
  for item in overrides:
    common.override(config, item)
  config.savi.train.steps = steps
  length, batch = config.savi.train.clip_length, config.savi.train.batch_size
  offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
  starts = np.concatenate([o + np.arange(n - length + 1) for o, n in zip(offsets, lengths)])
  comp = pretrain.compiled(config)
  state = comp.init_state(jax.random.key(0), (batch, length, *image.shape[1:]))
  rng, pool, n, frames = np.random.default_rng(0), comp.model.input_pool, 6, 12
  start, losses = time.time(), []
  for step in range(1, steps + 1):
    clips = rng.choice(starts, batch)
    state, metrics = comp.train_step(state, image[clips[:, None] + np.arange(length)], None, jax.random.key(1))
    losses.append(float(metrics["loss"]))
    if step % int(os.environ.get("EVERY", 500)) == 0 or step == steps:
      out = jax.device_get(comp.eval_video(state["params"], val_image[:n, :frames]))
      masks = decomposition.upsample_masks(out["masks"], pool)
      ari = np.mean([decomposition.fg_ari(val_seg[i, :frames], masks[i]) for i in range(n)])
      if os.environ.get("SAVE"):                      # a path prefix: params and argmax masks at every evaluation
        save(os.environ["SAVE"], state["params"], val_image[:4, 0], masks[:4, 0].argmax(axis=1), val_seg[:4, 0])
      print(f"step {step}: loss {np.mean(losses[-50:]):.4f}  val FG-ARI {ari:.3f}  "
            f"max-over-slots mask {masks.max(axis=2).mean():.3f}  {time.time() - start:.0f} s", flush=True)
  params = state["params"]
  video = val_image[:n, :frames].astype(np.float32) / 255.0
  out, inter = comp.model.apply({"params": params}, video, init_slots=comp.initial_slots(params, n),
                                mutable=["intermediates"])
  attention = np.asarray(jax.tree.leaves(inter)[-1])          # [B, T, K, N], the last iteration
  side = int(np.sqrt(attention.shape[-1]))
  attention = decomposition.upsample_masks(attention.reshape(*attention.shape[:3], side, side),
                                          val_seg.shape[-1] // side)
  masks = decomposition.upsample_masks(out["masks"], pool)
  seg = val_seg[:n, :frames]
  print("FG-ARI, decoder masks, frames 0-11:", round(np.mean([decomposition.fg_ari(seg[i], masks[i]) for i in range(n)]), 3))
  print("FG-ARI, decoder masks, frame 0:    ",
        round(np.mean([decomposition.fg_ari(seg[i, :1], masks[i, :1]) for i in range(n)]), 3))
  print("FG-ARI, attention maps, frame 0:   ",
        round(np.mean([decomposition.fg_ari(seg[i, :1], attention[i, :1]) for i in range(n)]), 3))
  slots = np.asarray(out["slots"])
  print("slot spread (std over slots / mean |slot|) per frame:",
        np.round(slots.std(axis=2).mean(axis=(0, 2)) / np.abs(slots).mean(), 3).tolist())


if __name__ == "__main__":
  main(int(sys.argv[1]), sys.argv[2:])
