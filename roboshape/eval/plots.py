"""Figures: the paper's overall figure (mean success rate per encoder and generalization level, averaged over
tasks). Training curves of validation metrics are drawn by roboshape/train/history.py."""
import os
from typing import Dict, List, Sequence

import numpy as np

from roboshape import fileio
from roboshape.envs.palettes import LEVEL_NAMES
from roboshape.eval import tables


def overall_means(summary: Sequence[Dict], levels: Sequence[str] = LEVEL_NAMES) -> Dict[str, List[float]]:
  """{encoder: [mean over tasks of the success rate at each level]} (NaN where no task has that cell)."""
  encoders = tables.sort_encoders(list(dict.fromkeys(r["encoder"] for r in summary)))
  out = {}
  for encoder in encoders:
    values = []
    for level in levels:
      means = [r["mean"] for r in summary if r["encoder"] == encoder and r["level"] == level and r["mean"] is not None]
      values.append(float(np.mean(means)) if means else float("nan"))
    out[encoder] = values
  return out


def overall_bar_chart(summary: Sequence[Dict], path: str, levels: Sequence[str] = LEVEL_NAMES,
                      title: str = "Overall success rate (mean over tasks)") -> str:
  """Writes a grouped bar chart PNG (x: levels, one bar per encoder) to `path`; returns `path`."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

  means = overall_means(summary, levels)
  x = np.arange(len(levels))
  width = 0.8 / max(len(means), 1)
  fig, ax = plt.subplots(figsize=(5.5, 3.2), dpi=150)
  for i, (encoder, values) in enumerate(means.items()):
    bars = ax.bar(x + (i - (len(means) - 1) / 2) * width, np.nan_to_num(values), width,
                  label=tables.encoder_name(encoder))
    for bar, v in zip(bars, values):
      if not np.isnan(v):
        ax.text(bar.get_x() + bar.get_width() / 2, bar.get_height() + 0.01, f"{v:.2f}", ha="center",
                va="bottom", fontsize=6)
  ax.set_xticks(x, [tables.level_name(l) for l in levels])
  ax.set_ylim(0, 1.05)
  ax.set_ylabel("success rate")
  ax.set_xlabel("generalization level")
  ax.set_title(title, fontsize=9)
  ax.legend(fontsize=7, frameon=False)
  ax.spines[["top", "right"]].set_visible(False)
  fig.tight_layout()
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  try:
    fileio.atomic_write_file(path, lambda f: fig.savefig(f, format=os.path.splitext(path)[1][1:]))
  finally:
    plt.close(fig)
  return path
