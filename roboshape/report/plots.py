"""Figures: the paper's overall figure (mean success rate per encoder and generalization level, averaged over
tasks) and its per-task figure with the report's 95% intervals as error bars. Training curves of validation metrics
are drawn by roboshape/train/history.py."""
from typing import Dict, List, Sequence, Tuple

import numpy as np

from roboshape import fileio
from roboshape.envs.palettes import LEVEL_NAMES
from roboshape.report import tables


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


def overall_tasks(summary: Sequence[Dict]) -> Dict[str, List[str]]:
  """{encoder: the tasks its overall means average over} (those it has a cell on), in the summary's order."""
  out = {}
  for r in summary:
    tasks = out.setdefault(r["encoder"], [])
    if r["task"] not in tasks:
      tasks.append(r["task"])
  return out


def tasks_differ(tasks: Dict[str, List[str]]) -> bool:
  """Whether the encoders of overall_tasks average over different tasks (then their overall means do not compare)."""
  return len({tuple(t) for t in tasks.values()}) > 1


def overall_bar_chart(summary: Sequence[Dict], path: str, levels: Sequence[str] = LEVEL_NAMES,
                      title: str = "Overall success rate (mean over tasks)") -> str:
  """Writes a grouped bar chart PNG (x: levels, one bar per encoder) to `path`; returns `path`."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

  means, tasks = overall_means(summary, levels), overall_tasks(summary)
  mixed = tasks_differ(tasks)                             # encoders averaged over different tasks: say which
  x = np.arange(len(levels))
  width = 0.8 / max(len(means), 1)
  fig, ax = plt.subplots(figsize=(7.0, 3.2), dpi=150)
  for i, (encoder, values) in enumerate(means.items()):
    bars = ax.bar(x + (i - (len(means) - 1) / 2) * width, np.nan_to_num(values), width,
                  label=tables.encoder_name(encoder) + (f" ({', '.join(tasks[encoder])})" if mixed else ""))
    for bar, v in zip(bars, values):
      if not np.isnan(v):
        ax.text(bar.get_x() + bar.get_width() / 2, bar.get_height() + 0.01, f"{v:.2f}", ha="center",
                va="bottom", fontsize=6)
  ax.set_xticks(x, [tables.level_name(l) for l in levels])
  ax.set_ylim(0, 1.05)
  ax.set_ylabel("success rate")
  ax.set_xlabel("generalization level")
  ax.set_title(title, fontsize=9)
  ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.0, 1.0))   # beside the bars, not on them
  ax.spines[["top", "right"]].set_visible(False)
  return fileio.save_figure(fig, path)


ZERO_DOT = 0.012   # the height of the dot that marks a measured success of 0 (levels_with_intervals)


def bar_layout(values: Dict[Tuple[str, str, str], Tuple], task: str, encoders: Sequence[str],
               levels: Sequence[str]) -> List[Tuple[str, float, float, int]]:
  """(encoder, offset from the level's tick, bar width, colour index) of each bar of `task`'s panel: the encoders
  with a cell on the task, side by side in `encoders`' order and filling the level's 0.8 of the axis; an encoder's
  colour is its index in `encoders`, the same in every panel."""
  present = [e for e in encoders if any((task, e, l) in values for l in levels)]
  width = 0.8 / max(len(present), 1)
  return [(e, (j - (len(present) - 1) / 2) * width, width, list(encoders).index(e)) for j, e in enumerate(present)]


def levels_with_intervals(values: Dict[Tuple[str, str, str], Tuple[float, float, float]], tasks: Sequence[str],
                          encoders: Sequence[str], levels: Sequence[str], path: str) -> str:
  """Writes the per-task figure to `path`: one panel per task, x the levels, one bar per encoder at its success
  with an error bar over its interval, and a dot of the bar's colour just above the axis where the success is 0, so
  a measured 0 is told from a cell that is not there. values: {(task, encoder, level): (value, low, high)}, NaN
  bounds drawing no error bar; a missing key draws no bar and no dot. Returns `path`."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

  encoders = tables.sort_encoders(list(encoders))
  x = np.arange(len(levels))
  fig, axes = plt.subplots(1, len(tasks), figsize=(3.2 * len(tasks) + 0.8, 3.0), dpi=150, squeeze=False,
                           sharey=True)
  for ax, task in zip(axes[0], tasks):
    for encoder, offset, width, colour in bar_layout(values, task, encoders, levels):
      cells = [values.get((task, encoder, l)) for l in levels]
      value, low, high = (np.array([np.nan if c is None else c[k] for c in cells]) for k in range(3))
      errors = np.nan_to_num(np.stack([value - low, high - value]))
      ax.bar(x + offset, np.nan_to_num(value), width, yerr=errors, capsize=2, error_kw=dict(elinewidth=0.8),
             label=tables.encoder_name(encoder), color=f"C{colour}")
      zero = np.flatnonzero(value == 0)        # a measured 0 has no height to see: a dot of its colour on the axis
      ax.plot(x[zero] + offset, np.full(len(zero), ZERO_DOT), marker="o", markersize=2.5, linestyle="none",
              color=f"C{colour}")
    ax.set_xticks(x, [tables.level_name(l) for l in levels])
    ax.set_ylim(0, 1.05)
    ax.set_title(task, fontsize=9)
    ax.set_xlabel("generalization level")
    ax.spines[["top", "right"]].set_visible(False)
  axes[0][0].set_ylabel("success rate (95% interval)")
  handles, labels = axes[0][0].get_legend_handles_labels()
  for ax in axes[0][1:]:
    for h, l in zip(*ax.get_legend_handles_labels()):
      if l not in labels:
        handles.append(h)
        labels.append(l)
  fig.legend(handles, labels, fontsize=7, frameon=False, loc="center right")
  return fileio.save_figure(fig, path, rect=(0, 0, 1 - 0.8 / (3.2 * len(tasks) + 0.8), 1))
