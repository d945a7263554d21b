"""Validation history of a training run: a JSON list of results per step, kept across resumes, and its curve.

  history.record(root, "val_metrics", step, {"fg_ari": 0.5, "miou": 0.4}, train_seconds, keys=("fg_ari", "miou"))
  -> <root>/val_metrics.json  [{"step": ..., "train_seconds": ..., "fg_ari": ..., ...}, ...]
     <root>/val_metrics.png   the keys against the step (`metric_curve`)
"""
import json
import os
from typing import Dict, List, Sequence

import numpy as np

from roboshape import fileio


def load(root: str, name: str) -> List[Dict[str, float]]:
  """The results <root>/<name>.json holds (an empty list before the first)."""
  path = os.path.join(root, f"{name}.json")
  if not os.path.exists(path):
    return []
  with open(path) as f:
    return json.load(f)


def seconds_at(root: str, name: str, step: int) -> float:
  """Training seconds recorded at the last result at or before `step` (0 if none): where a resumed run's clock
  starts."""
  earlier = [h["train_seconds"] for h in load(root, name) if h["step"] <= step]
  return earlier[-1] if earlier else 0.0


def record(root: str, name: str, step: int, metrics: Dict[str, float], train_seconds: float,
           keys: Sequence[str], title: str = "", ylim=None) -> List[Dict[str, float]]:
  """Adds the result at `step` to <root>/<name>.json and redraws <root>/<name>.png; returns the history.

  Results at or after `step` (left by a run killed after them and resumed from an earlier checkpoint) are
  replaced. train_seconds: wall seconds of training up to `step`, summed over the runs that made it.
  """
  history = [h for h in load(root, name) if h["step"] < step]
  history.append({"step": int(step), "train_seconds": round(float(train_seconds), 1),
                  **{k: float(v) for k, v in metrics.items()}})
  os.makedirs(root, exist_ok=True)
  fileio.atomic_write_json(os.path.join(root, f"{name}.json"), history)
  metric_curve(history, keys, os.path.join(root, f"{name}.png"),
               title=f"{title} (step {step}, {train_seconds / 60:.0f} min of training)", ylim=ylim)
  return history


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
  return fileio.save_figure(fig, path)


def overlay_curves(histories: Dict[str, Sequence[Dict]], key: str, path: str, title: str = "") -> str:
  """Writes a PNG of one metric of several runs, one line per run ({label: history}, as `load` returns), to
  `path`; returns `path` (e.g. every seed's FG-ARI, roboshape/train/pretrain.py)."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

  fig, ax = plt.subplots(figsize=(5.0, 3.2), dpi=150)
  for label, history in histories.items():
    ax.plot([h["step"] for h in history], [h.get(key, float("nan")) for h in history], marker="o", markersize=3,
            label=label, linewidth=2.2 if "selected" in label else 1.2)
  ax.set_xlabel("training step")
  ax.set_ylabel(key)
  ax.grid(alpha=0.3)
  ax.spines[["top", "right"]].set_visible(False)
  ax.legend(fontsize=7)
  ax.set_title(title, fontsize=8)
  return fileio.save_figure(fig, path)
