"""Figures: the paper's overall figure (mean success rate per encoder and generalization level, averaged over
tasks) and training curves of metrics over steps."""
import os
from typing import Dict, List, Sequence

import numpy as np

from roboshape.eval import tables


def overall_means(summary: Sequence[Dict], levels: Sequence[str] = tables.LEVELS) -> Dict[str, List[float]]:
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


def overall_bar_chart(summary: Sequence[Dict], path: str, levels: Sequence[str] = tables.LEVELS,
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
  fig.savefig(path)
  plt.close(fig)
  return path


def metric_curve(history: Sequence[Dict], keys: Sequence[str], path: str, title: str = "", ylim=None) -> str:
  """Writes a PNG of history[i][key] against history[i]["step"], one panel per key, to `path`; returns `path`.

  ylim: (low, high) for every panel, either None for matplotlib's choice; (None, 1.0) suits scores <= 1 (the panel
  then starts at 0, or lower if a score is negative).
  """
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

  steps = [h["step"] for h in history]
  fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 2.8), dpi=150, squeeze=False)
  for ax, key in zip(axes[0], keys):
    values = [h.get(key, float("nan")) for h in history]
    ax.plot(steps, values, marker="o", markersize=3)
    ax.set_xlabel("training step")
    ax.set_title(key, fontsize=8)
    if ylim is not None:
      finite = [v for v in values if np.isfinite(v)]
      ax.set_ylim(ylim[0] if ylim[0] is not None else min([0.0] + finite), ylim[1])
    ax.grid(alpha=0.3)
    ax.spines[["top", "right"]].set_visible(False)
  fig.suptitle(title, fontsize=9)
  fig.tight_layout()
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  fig.savefig(path)
  plt.close(fig)
  return path
