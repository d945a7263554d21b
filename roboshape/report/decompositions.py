"""How well each object-centric encoder of a report decomposes its task's frames: the final pretraining validation
of the encoder a cell's policy was trained on (its selected seed where there were several).

FG-ARI is dominated by the large masks (backdrop, table, arm); the per-object columns say whether the small task
objects get a slot of their own: for the cube, the target (or bin) and the hand, the best IoU of any slot's mask
with the object's mask, averaged over validation frames, and the share of frames in which one slot covers the cube
with IoU >= 0.5 (roboshape/eval/slots.py computes them). A run validated before those measures existed has "-".
"""
import json
import math
import os
from typing import Dict, List, Optional, Sequence, Tuple

from roboshape import rundir
from roboshape.encoders import columns
from roboshape.encoders import registry

COLUMNS = (("fg_ari", "FG-ARI"), ("miou", "mIoU"), ("cube_iou", "cube IoU"), ("cube_found", "cube found"),
           ("goal_iou", "target IoU"), ("hand_iou", "hand IoU"))


def _last(path: str, selected: bool) -> Optional[Dict]:
  """The final validation in a val_metrics.json (a list), or in a selected.json (the selected seed's entry)."""
  if not os.path.isfile(path):
    return None
  try:
    with open(path) as f:
      data = json.load(f)
  except (OSError, ValueError):
    return None
  if selected and isinstance(data, dict):
    data = [s for s in data.get("seeds", []) if s.get("seed") == data.get("selected_seed")]
  return data[-1] if isinstance(data, list) and data and isinstance(data[-1], dict) else None


def final_validation(folder: str, encoder: str) -> Optional[Dict]:
  """The final pretraining validation of the encoder served to the run in `folder` (a published cell's folder,
  <encoder>_selected_val_metrics.json or <encoder>_val_metrics.json, or a workdir's <encoder>/ folder); None where
  there is none."""
  for path, selected in ((os.path.join(folder, f"{encoder}_selected_val_metrics.json"), False),
                         (os.path.join(folder, f"{encoder}_val_metrics.json"), False),
                         (rundir.selection_path(rundir.pretrain_dir(folder, encoder)), True),
                         (os.path.join(rundir.pretrain_dir(folder, encoder), "val_metrics.json"), False)):
    found = _last(path, selected)
    if found is not None:
      return found
  return None


def _cell(metrics: Dict, key: str) -> str:
  value = metrics.get(key)
  if not isinstance(value, (int, float)) or math.isnan(value):
    return "-"
  return f"{value:.0%}" if key == "cube_found" else f"{value:.2f}"


def table(runs: Sequence[Tuple[str, str, str]], name) -> List[str]:
  """Markdown lines of the decomposition table over the `runs` (task, column, folder) whose encoder is scored by
  slot decompositions (registry Kind.evaluator "slots"); `name` gives a column's printed name. [] for none."""
  rows = []
  for task, column, folder in runs:
    encoder = columns.parse(column)[0]
    if registry.get(encoder).evaluator != "slots":
      continue
    metrics = final_validation(folder, encoder)
    if metrics is not None:
      rows.append(f"| {task} x {name(column)} | " + " | ".join(_cell(metrics, k) for k, _ in COLUMNS) + " |")
  if not rows:
    return []
  return (["| | " + " | ".join(title for _, title in COLUMNS) + " |", "| --- |" + " --- |" * len(COLUMNS)]
          + rows)
