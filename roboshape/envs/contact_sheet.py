"""A contact sheet: the first frame of every task under every level, for several seeds, in one PNG.

  python -m roboshape.envs.contact_sheet --out results/contact_sheet.png [--seeds 4] [--resolution 128]
      [--segmentation]

Rows are task x level, columns are seeds (the same seeds in every row, so a column shows one layout under the four
levels). With --segmentation each frame is followed by its object-id map. Renders in this process (never
import TensorFlow next to it).
"""
import argparse
import sys

from roboshape import envs
from roboshape import errors
from roboshape import fileio
from roboshape.envs import ids


def render_frames(tasks, levels, seeds, resolution: int, segmentation: bool):
  """{(task, level): [uint8 [H, W, 3], ...]} first frames (and colored segmentations) per seed."""
  frames = {}
  for task in tasks:
    for level in levels:
      env = envs.make_env(task, level, resolution=resolution)
      row = []
      for seed in seeds:
        obs, _ = env.reset(seed=seed)
        rgb, seg = env.unwrapped.frames(obs)
        row.append(rgb[0])
        if segmentation:
          row.append(ids.colorize(seg[0]))
      env.close()
      frames[(task, level)] = row
      print(f"rendered {task} / {level}", flush=True)
  return frames


def save_sheet(frames, seeds, path: str, segmentation: bool) -> None:
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  rows = list(frames)
  cols = len(next(iter(frames.values())))
  fig, axes = plt.subplots(len(rows), cols, figsize=(1.6 * cols, 1.6 * len(rows)), squeeze=False)
  for r, (task, level) in enumerate(rows):
    for c, image in enumerate(frames[(task, level)]):
      ax = axes[r][c]
      ax.imshow(image, interpolation="nearest")
      ax.set_xticks([])
      ax.set_yticks([])
      if r == 0:
        seed = seeds[c // 2] if segmentation else seeds[c]
        ax.set_title(f"seed {seed}" + (" seg" if segmentation and c % 2 else ""), fontsize=8)
      if c == 0:
        ax.set_ylabel(f"{task}\n{level}", fontsize=9)
  fileio.save_figure(fig, path, dpi=100)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--out", default="results/contact_sheet.png")
  parser.add_argument("--seeds", type=int, default=4, help="number of seeds per cell (0, 1, ...)")
  parser.add_argument("--first_seed", type=int, default=0)
  parser.add_argument("--resolution", type=int, default=128)
  parser.add_argument("--tasks", default=",".join(envs.TASKS))
  parser.add_argument("--levels", default=",".join(envs.LEVEL_NAMES))
  parser.add_argument("--segmentation", action="store_true", help="add each frame's object-id map")
  args = parser.parse_args(argv)
  tasks, levels = args.tasks.split(","), args.levels.split(",")
  try:
    for task in tasks:
      for level in levels:
        envs.check_args(task, level, args.resolution)
  except ValueError as e:
    return errors.print_error(e)
  seeds = list(range(args.first_seed, args.first_seed + args.seeds))
  try:
    frames = render_frames(tasks, levels, seeds, args.resolution, args.segmentation)
  except RuntimeError as e:
    return errors.print_error(envs.explain_construction_error(e))
  save_sheet(frames, seeds, args.out, args.segmentation)
  print(f"contact sheet: {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
