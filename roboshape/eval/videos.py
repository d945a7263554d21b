"""Rollout videos: MP4 (imageio-ffmpeg) and GIF files of camera frames, optionally beside other panels.

  paths = write_video(frames, "eval/videos/L1_seed1000000003", fps=20)   # frames uint8 [T, H, W, 3]
"""
import os
from typing import List, Sequence

import numpy as np

from roboshape.errors import UserError


def upscale(frames: np.ndarray, factor: int) -> np.ndarray:
  """Nearest-neighbour upscaling of [T, H, W, C] frames (any dtype) by an integer factor (64 px frames are tiny)."""
  if factor <= 1:
    return frames
  return np.repeat(np.repeat(frames, factor, axis=1), factor, axis=2)


def side_by_side(panels: Sequence[np.ndarray], gap: int = 2) -> np.ndarray:
  """Concatenates uint8 [T, H, W_i, 3] videos of equal T and H along width, with white gaps: [T, H, sum W, 3]."""
  t, h = panels[0].shape[:2]
  spacer = np.full((t, h, gap, 3), 255, np.uint8)
  parts = []
  for i, p in enumerate(panels):
    if p.shape[:2] != (t, h):
      raise ValueError(f"panel {i} has shape {p.shape}, expected [T={t}, H={h}, ...]")
    parts += ([spacer] if i else []) + [p.astype(np.uint8)]
  return np.concatenate(parts, axis=2)


FORMATS = ("mp4", "gif")
_PARTIAL = ".tmp."     # `stem`.tmp.mp4: a video being written (the extension tells imageio the format)


def exists(stem: str, formats: Sequence[str] = FORMATS) -> bool:
  """Whether a video `stem`.<format> was written (in any of `formats`)."""
  return any(os.path.isfile(f"{stem}.{fmt}") for fmt in formats)


def remove_partial(directory: str) -> List[str]:
  """Deletes the half-written videos a killed `write_video` left in `directory`; returns their names."""
  if not os.path.isdir(directory):
    return []
  partial = sorted(n for n in os.listdir(directory) if any(n.endswith(f"{_PARTIAL}{fmt}") for fmt in FORMATS))
  for name in partial:
    os.remove(os.path.join(directory, name))
  return partial


def write_video(frames: np.ndarray, stem: str, fps: int = 20, scale: int = 4,
                formats: Sequence[str] = FORMATS) -> List[str]:
  """Writes `stem`.mp4 and `stem`.gif from uint8 [T, H, W, 3]; returns the paths written.

  Each file is written under a temporary name and renamed into place, so a video is either whole or absent.
  A format whose writer is unavailable (e.g. no ffmpeg) is skipped with a warning rather than failing the run.
  """
  # imageio-ffmpeg starts ffmpeg with preexec_fn=os.setpgrp (to keep Ctrl-C from it) unless this is set: Python run
  # between fork and exec, in a process holding JAX's threads, can deadlock. An interrupted video is discarded anyway.
  os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  frames = upscale(np.asarray(frames, np.uint8), scale)
  # H.264 wants even sizes that are multiples of 16 for most players: pad with white.
  h, w = frames.shape[1:3]
  ph, pw = (-h) % 16, (-w) % 16
  if ph or pw:
    frames = np.pad(frames, ((0, 0), (0, ph), (0, pw), (0, 0)), constant_values=255)
  os.makedirs(os.path.dirname(stem) or ".", exist_ok=True)
  written = []
  for fmt in formats:
    path, tmp = f"{stem}.{fmt}", f"{stem}{_PARTIAL}{fmt}"
    try:
      if fmt == "mp4":
        imageio.mimwrite(tmp, list(frames), fps=fps, codec="libx264", quality=8, macro_block_size=16)
      elif fmt == "gif":
        imageio.mimwrite(tmp, list(frames), duration=1.0 / fps, loop=0)
      else:
        raise ValueError(f"unknown video format {fmt!r}")
      os.replace(tmp, path)
    except Exception as e:  # pylint: disable=broad-except
      print(f"[roboshape] warning: could not write {path}: {e}", flush=True)
      continue
    finally:
      if os.path.exists(tmp):
        os.remove(tmp)
    written.append(path)
  return written


class SaviSlotVideo:
  """The SAVi slot decomposition of a rollout beside its camera frames (the paper's Figure 8, as a video).

    make = SaviSlotVideo(workdir)        # loads the run's SAVi checkpoint on first use
    panels = make(frames)                # uint8 [T, H, W, 3] -> uint8 [T, H, (2 + K) * W + gaps, 3]

  Runs the run's frozen SAVi over the whole rollout from its first frame, as the policy saw it: the camera frame,
  the reconstruction, then each slot's reconstruction through its mask (roboshape.eval.decomposition.masked_slots).
  Episodes are padded to a multiple of `pad_multiple` frames (then cut) so that videos of different lengths share
  compilations (the recurrence is causal, so padding at the end changes nothing before it).
  """

  def __init__(self, workdir: str, pad_multiple: int = 32):
    self.workdir = workdir
    self.pad_multiple = pad_multiple
    self._loaded = None

  def __call__(self, frames: np.ndarray) -> np.ndarray:
    # pylint: disable=import-outside-toplevel
    import jax
    from roboshape.encoders import savi as savi_encoder
    from roboshape.eval import decomposition
    from roboshape.models import savi
    if self._loaded is None:
      model, params, _ = savi_encoder.load(self.workdir)
      self._loaded = (model, params)
    model, params = self._loaded
    if savi.conditional(model):
      raise UserError("a conditional SAVi starts from the rollout's first segmentation, which the recorder does not "
                      "keep: its slot videos are not made")
    frames = np.asarray(frames, np.uint8)
    t = frames.shape[0]
    padded = np.concatenate([frames, np.repeat(frames[-1:], (-t) % self.pad_multiple, axis=0)])
    out = jax.device_get(savi.decompose(model, params, padded[None]))
    recon = np.clip(out["recon"][0, :t], 0.0, 1.0)                                  # [T, h, w, 3]
    slots = decomposition.masked_slots(out["rgb"][0, :t], out["masks"][0, :t])     # [T, K, h, w, 3]
    pool = model.input_pool                                                         # h = H / pool
    to_u8 = lambda x: (upscale(np.asarray(x), pool) * 255.0 + 0.5).astype(np.uint8)
    panels = [frames, to_u8(recon)] + [to_u8(slots[:, k]) for k in range(slots.shape[1])]
    return side_by_side(panels)
