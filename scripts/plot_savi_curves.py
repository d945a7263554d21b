"""Draws the validation FG-ARI and reconstruction MSE of several SAVi runs side by side into one PNG.

  .venv/bin/python scripts/plot_savi_curves.py RUN.json [RUN.json ...] --out curves.png [--bar 0.6] [--mse-max 0.08]
  e.g. ... scripts/plot_savi_curves.py results/savi_small/*.json --out results/savi_small/fg_ari_curves.png \
      --bar 0.6 --mse-max 0.08

Each RUN.json is a run's <workdir>/savi/val_metrics.json (a list of {"step", "fg_ari", "recon_mse", ...}, one per
evaluation), or a copy of one; the legend names each curve by its file name (a val_metrics.json by its workdir).
The pretrain stage draws one run's curves itself (<workdir>/savi/val_metrics.png); this compares runs.
"""
import argparse
import json
import os

import matplotlib

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # pylint: disable=wrong-import-position


def label(path):
  """The legend of a run: its file name, or its workdir's name for a <workdir>/savi/val_metrics.json (and the seed
  for a <workdir>/savi/seed_<s>/val_metrics.json of pretrain.train_seeds)."""
  name = os.path.splitext(os.path.basename(path))[0]
  if name == "val_metrics":
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.basename(folder).startswith("seed_"):
      return f"{os.path.basename(os.path.dirname(os.path.dirname(folder)))} {os.path.basename(folder)}"
    return os.path.basename(os.path.dirname(folder))
  return name


def main(args):
  legend_height = 0.16 * -(-len(args.runs) // 3)                      # inches: three legend entries a row
  height = 4.0 + legend_height
  fig, axes = plt.subplots(1, 2, figsize=(12, height), dpi=130)
  colours = plt.get_cmap("tab20")
  for i, path in enumerate(args.runs):
    with open(path) as f:
      history = json.load(f)
    steps = [h["step"] for h in history]
    style = dict(marker="o", markersize=2.5, color=colours(i % 20), linestyle="-" if i < 20 else "--",
                 label=label(path), linewidth=1.2)
    axes[0].plot(steps, [h["fg_ari"] for h in history], **style)
    if all("recon_mse" in h for h in history):
      axes[1].plot(steps, [h["recon_mse"] for h in history], **style)
  if args.bar is not None:
    axes[0].axhline(args.bar, color="grey", linestyle="--", linewidth=1)
  if args.mse_max:
    axes[1].set_ylim(0.0, args.mse_max)
  axes[0].set_ylabel("validation FG-ARI")
  axes[1].set_ylabel("validation reconstruction MSE")
  for ax in axes:
    ax.set_xlabel("training step")
    ax.grid(alpha=0.3)
  fig.legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="lower center", ncol=3, frameon=False)
  fig.subplots_adjust(bottom=(legend_height + 0.6) / height, top=1 - 0.35 / height, wspace=0.22)
  if args.title:
    fig.suptitle(args.title)
  fig.savefig(args.out)
  print(args.out)


if __name__ == "__main__":
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("runs", nargs="+", help="val_metrics.json files, one per run")
  parser.add_argument("--out", required=True, help="the PNG to write")
  parser.add_argument("--bar", type=float, default=None, help="draw a horizontal line at this FG-ARI")
  parser.add_argument("--mse-max", type=float, default=0.0, help="upper limit of the MSE axis (0: automatic)")
  parser.add_argument("--title", default="", help="the figure's title")
  main(parser.parse_args())
