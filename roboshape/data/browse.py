"""Looks at one episode of a RoboShape dataset: an animation (GIF or MP4) and a PNG strip of frames.

  python -m roboshape.data.browse PATH --split train --episode 0 --out ep0.gif     # also writes ep0_strip.png
  python -m roboshape.data.browse PATH --episode 3 --out ep3.mp4 --scale 6 --frames 10

Each frame shows every camera's image next to its segmentation (object ids in fixed colours), the front camera's
first and the others' after it (roboshape/envs/camera.py); --no-segmentation leaves the segmentation out. PATH is the dataset directory, or a workdir / data folder that holds one dataset.
"""
import argparse
import itertools
import os
import sys
from typing import Dict

import numpy as np

from roboshape import errors
from roboshape.errors import UserError
from roboshape.envs import camera
from roboshape.envs import ids

colorize = ids.colorize   # one colour per segmentation id


def frames_of(episode: Dict[str, np.ndarray], scale: int = 4, segmentation: bool = True) -> np.ndarray:
  """uint8 [S, H*scale, (W*(1 or 2) + gaps)*scale, 3]: each stored camera's image (and segmentation) of every
  step, side by side with white gaps, upscaled."""
  gap = np.full(episode["image"].shape[:2] + (1, 3), 255, np.uint8)
  panels = []
  for name in camera.CAMERAS:
    image_key, seg_key, _ = camera.keys(name)
    if image_key in episode:
      panels += [gap, episode[image_key]] + ([gap, colorize(episode[seg_key])] if segmentation else [])
  frames = np.concatenate(panels[1:], axis=2)
  return frames.repeat(scale, axis=1).repeat(scale, axis=2)


def strip(frames: np.ndarray, count: int) -> np.ndarray:
  """`count` frames evenly spaced from first to last, side by side with a white gap: uint8 [H, W', 3]."""
  index = np.unique(np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int))
  gap = np.full((frames.shape[1], 4, 3), 255, np.uint8)
  return np.concatenate([x for i in index for x in (frames[i], gap)][:-1], axis=1)


def write(episode: Dict[str, np.ndarray], out: str, scale: int = 4, fps: int = 10, strip_frames: int = 8,
          segmentation: bool = True) -> Dict[str, str]:
  """Writes the episode to `out` (.gif or .mp4) and a PNG strip next to it; returns both paths."""
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  ext = os.path.splitext(out)[1].lower()
  if ext not in (".gif", ".mp4"):
    raise UserError(f"--out {out!r}: use a .gif or .mp4 file name.")
  frames = frames_of(episode, scale, segmentation)
  os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
  if ext == ".gif":
    imageio.mimsave(out, list(frames), duration=1000 / fps, loop=0)
  else:
    pad = (-frames.shape[1] % 16, -frames.shape[2] % 16)  # codec-friendly size
    frames = np.pad(frames, ((0, 0), (0, pad[0]), (0, pad[1]), (0, 0)))
    imageio.mimsave(out, list(frames), fps=fps, macro_block_size=1)
  strip_path = os.path.splitext(out)[0] + "_strip.png"
  imageio.imwrite(strip_path, strip(frames, strip_frames))
  return {"animation": out, "strip": strip_path}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m roboshape.data.browse", description=__doc__.splitlines()[0])
  parser.add_argument("path", help="the dataset directory, or a workdir / data folder holding one dataset")
  parser.add_argument("--split", default="train", choices=("train", "val"))
  parser.add_argument("--episode", type=int, default=0, help="index of the episode within the split")
  parser.add_argument("--out", default="episode.gif", help="output .gif or .mp4 (the strip goes to <out>_strip.png)")
  parser.add_argument("--scale", type=int, default=4, help="pixel upscaling factor")
  parser.add_argument("--fps", type=int, default=10)
  parser.add_argument("--frames", type=int, default=8, help="frames in the PNG strip")
  parser.add_argument("--no-segmentation", action="store_true", help="show the camera image only")
  args = parser.parse_args(argv)
  try:
    from roboshape.data import reader  # pylint: disable=import-outside-toplevel
    from roboshape.data import validate  # pylint: disable=import-outside-toplevel
    path = validate.find_dataset(args.path)
    if args.episode < 0:
      raise UserError("--episode must be >= 0.")
    episode = next(itertools.islice(reader.read_episodes(path, args.split, allow_incomplete=True),
                                    args.episode, None), None)
    if episode is None:
      raise UserError(f"split {args.split!r} of {path} has fewer than {args.episode + 1} episodes.")
    written = write(episode, args.out, args.scale, args.fps, args.frames, not args.no_segmentation)
  except UserError as e:
    return errors.print_error(e)
  print(f"seed {episode['seed']}: {episode['image'].shape[0]} steps -> {written['animation']}, {written['strip']}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
