"""Copies a finished run's results out of its workdir, so they survive the machine (e.g. into results/small/).

  python -m roboshape.report.publish RUN_WORKDIR DEST_ROOT    # one evaluated run, e.g. into results/small
  publish(config, workdir, dest_root)  ->  <dest_root>/<task>_<column>/
  check_datasets({(task, column): folder})   # UserError when cells of one task name different datasets
                                             # (publish refuses a cell that would make its row such a mix)
  datasets({(task, column): folder})         # {task: {identity: [folders]}}, what the report lists per task
  record_grid(dest_root, tasks, columns); record_skip(dest_root, task, column, reason); grid_record(dest_root)

The folder is named after the run's column (roboshape/encoders/columns.py): its encoder, with its options
("push_savi+proprio").

A grid config with `grid.publish` set (configs/reproduce.py:small: "results/small") publishes each run as soon as
its evaluation is complete. What is copied, under fixed names (files the run does not have are left out):

  config.json                      the config that ran
  dataset.json                     the identity of the dataset it was trained on (roboshape.data.record: a hash
                                   over its shards' checksums, the same for every copy of the dataset)
  stages.json                      each stage's wall time (roboshape.status reads it)
  results.csv, table.md, table.tex, success_by_level.png, milestones.md   eval/: every rollout, the tables, the
                                                                          plot, how far the rollouts got
  policy_val_metrics.json/.png     the policy's validation curve (with policy.train_seeds, one per seed s:
                                   policy_seed_<s>_val_metrics.json/.png)
  <encoder>_val_metrics.json/.png  the encoder's pretraining curve (savi, ae), and its seed selection files (from
                                   the run that pretrained it: pretrain.from_workdir); with pretraining seeds, the
                                   selected seed's curve as <encoder>_selected_val_metrics.json/.png
  <encoder>_[selected_]step_<n>.png  the last figure the encoder's pretraining drew (SAVi: its slot decomposition
                                   of validation frames), of the selected seed where there are seeds
  videos/*.mp4                     the rollout videos the evaluation recorded (a few per level)

A grid that publishes also keeps <dest_root>/grid.json: its tasks and columns, and the one-line reason of each cell
it skipped (a baseline without weights), so the report over the folder lists the cells not published yet and the
skipped ones with their reasons while the grid is part way. A grid run over part of the cells (one task's row, or
the cells still to do after a machine lost the grid's workdir) adds its tasks and columns to the record and never
narrows it: delete grid.json to start a record anew.

Files of an earlier publication of the same run that this one does not replace are removed, so the folder always
holds one run; a README.md written there by hand is kept while it is this run's (the folder's config.json is the
run's, or there is none yet), and goes with the files of another run that the folder held before.
"""
import glob
import json
import os
import shutil
import sys
from typing import Dict, List, Mapping, Tuple

from roboshape import data as data_lib
from roboshape import errors
from roboshape import fileio
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.errors import UserError

KEPT = ("README.md",)
GRID_FILE = "grid.json"    # <dest_root>/grid.json: {"tasks", "columns", "skipped": {"<task>_<column>": reason}}
DATASET = rundir.DATASET_FILE
EVAL_FILES = (rundir.RESULTS_CSV, "table.md", "table.tex", "success_by_level.png", "milestones.md")


def planned(config, workdir: str) -> List[tuple]:
  """(source path, name in the published folder) of every file `publish` copies from `workdir` (and from the
  workdir whose pretrain stage trained its encoder)."""
  pairs = [(rundir.config_path(workdir), "config.json"), (rundir.stage_log_path(workdir), "stages.json"),
           (rundir.dataset_record(workdir), DATASET)]
  pairs += [(os.path.join(rundir.eval_dir(workdir), name), name) for name in EVAL_FILES]
  for seed in rundir.train_seeds(config):
    policy, name = rundir.policy_dir(workdir, seed), "policy" if seed is None else f"policy_seed_{seed}"
    pairs += [(os.path.join(policy, f"val_metrics{ext}"), f"{name}_val_metrics{ext}") for ext in (".json", ".png")]
  encoder_dir = rundir.pretrain_dir(rundir.pretrained_workdir(config, workdir), config.encoder)
  for path in sorted(glob.glob(os.path.join(encoder_dir, "*.json")) + glob.glob(os.path.join(encoder_dir, "*.png"))):
    pairs.append((path, f"{config.encoder}_{os.path.basename(path)}"))
  selection = rundir.load_selection(encoder_dir)
  kept, prefix = encoder_dir, f"{config.encoder}_"
  if selection is not None:
    kept, prefix = rundir.seed_dir(encoder_dir, selection["selected_seed"]), f"{config.encoder}_selected_"
    pairs += [(os.path.join(kept, f"val_metrics{ext}"), f"{prefix}val_metrics{ext}") for ext in (".json", ".png")]
  figures = sorted(glob.glob(os.path.join(kept, rundir.FIGURES_DIR, "*.png")))
  if figures:   # the last validation's figures: step_<n>.png and, with several cameras, step_<n>_<camera>.png
    step = lambda path: os.path.basename(path).split(".")[0].split("_")[1]
    pairs += [(f, prefix + os.path.basename(f)) for f in figures if step(f) == step(figures[-1])]
  for path in sorted(glob.glob(os.path.join(rundir.videos_dir(workdir), "*.mp4"))):
    pairs.append((path, os.path.join("videos", os.path.basename(path))))
  return [(src, name) for src, name in pairs if os.path.isfile(src)]


def _same_run(published_config: str, run_config: str) -> bool:
  """Whether a folder's README may stay: it was written for this run (its published config.json is the run's), or
  ahead of any run (no config.json yet). Another run's README describes another run, so it goes with its files."""
  if not os.path.isfile(published_config):
    return True
  try:
    with open(published_config) as a, open(run_config) as b:
      return json.load(a) == json.load(b)
  except (OSError, ValueError):
    return False


def publish(config, workdir: str, dest_root: str) -> str:
  """Copies the results of the run in `workdir` to <dest_root>/<task>_<column>/; returns that folder. A run without
  a dataset.json of its own (its collect stage ran before runs recorded one) gets one made from its dataset's
  roboshape.json where that dataset still is.

  Raises UserError when the run has no evaluation results yet, or when the cells of its task published in
  `dest_root` were trained on another dataset than it (nothing is copied then)."""
  if not os.path.exists(os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_FILE)):
    raise UserError(f"{workdir} has no evaluation results ({rundir.RESULTS_FILE}) to publish: run its evaluate "
                    "stage first.")
  dest = os.path.join(dest_root, f"{config.task}_{columns.of_config(config)}")
  pairs = planned(config, workdir)
  names = {name for _, name in pairs}
  record = None if DATASET in names else data_lib.read_record(data_lib.dataset_path(config, workdir))
  if record is not None:
    names.add(DATASET)
  own = record["identity"] if record is not None else (
      _identity(rundir.dataset_record(workdir)) if DATASET in names else None)
  _check_joins_its_row(config.task, columns.of_config(config), own, dest_root)
  if os.path.isdir(dest):
    kept = KEPT if _same_run(os.path.join(dest, "config.json"), rundir.config_path(workdir)) else ()
    for folder, _, files in os.walk(dest):
      for name in files:
        rel = os.path.relpath(os.path.join(folder, name), dest)
        if rel not in names and rel not in kept:
          os.remove(os.path.join(folder, name))
  for src, name in pairs:
    target = os.path.join(dest, name)
    os.makedirs(os.path.dirname(target), exist_ok=True)
    shutil.copyfile(src, target + ".partial")
    os.replace(target + ".partial", target)
  if record is not None:
    fileio.atomic_write_json(os.path.join(dest, DATASET), record)
  return dest


def _identity(path: str) -> str:
  """The identity a dataset.json at `path` records; a UserError when it cannot be read."""
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)["identity"]
  except (OSError, ValueError, KeyError, TypeError) as e:
    raise UserError(f"{path} is damaged ({type(e).__name__}): publish that run again from its workdir, or "
                    "restore the file from git.") from None


def _check_joins_its_row(task: str, column: str, identity, dest_root: str) -> None:
  """Raises UserError, before anything is copied, when the cells of `task` already published in `dest_root` (other
  than this column's) record another dataset than `identity`: publishing there would make the folder's report
  refuse the row (`check_datasets`). A run or cell without a recorded dataset is not compared."""
  if identity is None or not os.path.isdir(dest_root):
    return
  others = {}
  for name in sorted(os.listdir(dest_root)):
    folder = os.path.join(dest_root, name)
    if name == rundir.grid_cell(task, column) or not os.path.isfile(os.path.join(folder, DATASET)):
      continue
    try:
      with open(os.path.join(folder, "config.json"), encoding="utf-8") as f:
        if json.load(f).get("task") != task:
          continue
    except (OSError, ValueError, AttributeError):
      continue
    found = _identity(os.path.join(folder, DATASET))
    if found != identity:
      others.setdefault(found, []).append(name)
  if others:
    cells = "; ".join(f"{', '.join(names)} on {found}" for found, names in sorted(others.items()))
    raise UserError(f"{task} x {column} was trained on dataset {identity}, but the {task} cells in {dest_root} on "
                    f"another ({cells}): publish this row into another folder (--config.grid.publish) and move it "
                    "in once all its cells are done, or move the old cells out first.")


def datasets(cells: Mapping[Tuple[str, str], str]) -> Dict[str, Dict[str, List[str]]]:
  """{task: {dataset identity: [cell folders]}} of published cells ({(task, column): folder}), from their
  dataset.json; a cell without one (published before runs recorded one) is left out."""
  by_task: Dict[str, Dict[str, List[str]]] = {}
  for (task, _), folder in sorted(cells.items()):
    path = os.path.join(folder, DATASET)
    if os.path.isfile(path):
      by_task.setdefault(task, {}).setdefault(_identity(path), []).append(os.path.normpath(folder))
  return by_task


def check_datasets(cells: Mapping[Tuple[str, str], str]) -> Dict[str, Dict[str, List[str]]]:
  """`datasets(cells)`, after raising UserError, one line naming the cells, when published cells of one task
  ({(task, column): folder}) record different datasets (their dataset.json identities): such cells were trained on
  other demos and do not belong in one table. A cell without a dataset.json (published before runs recorded one)
  is not compared."""
  by_task = datasets(cells)
  for task, found in by_task.items():
    if len(found) > 1:
      groups = "; ".join(f"{', '.join(os.path.basename(f) for f in folders)} on dataset {identity}"
                         for identity, folders in sorted(found.items(), key=lambda kv: (-len(kv[1]), kv[0])))
      root = os.path.dirname(next(iter(found.values()))[0])
      raise UserError(f"the {task} cells were trained on different datasets ({groups}): publish every cell of a "
                      f"task from runs on one dataset (one grid), or move the odd cells out of {root}.")
  return by_task


def grid_record(dest_root: str) -> Dict:
  """<dest_root>/grid.json as {"tasks": [...], "columns": [...], "skipped": {"<task>_<column>": reason}}, or the
  empty record when no grid published there."""
  path = os.path.join(dest_root, GRID_FILE)
  if not os.path.isfile(path):
    return dict(tasks=[], columns=[], skipped={})
  try:
    with open(path, encoding="utf-8") as f:
      record = json.load(f)
    return dict(tasks=list(record["tasks"]), columns=list(record["columns"]), skipped=dict(record["skipped"]))
  except (OSError, ValueError, KeyError, TypeError) as e:
    raise UserError(f"{path} is damaged ({type(e).__name__}): delete it; the grid writes it again when it "
                    "starts.") from None


def record_grid(dest_root: str, tasks, grid_columns) -> None:
  """Adds to grid.json the tasks and columns of the grid publishing into `dest_root`, after those noted already
  (a grid over part of the cells never narrows the record), keeping the skips noted."""
  record = grid_record(dest_root)
  _write_grid(dest_root, dict(tasks=list(dict.fromkeys(record["tasks"] + list(tasks))),
                              columns=list(dict.fromkeys(record["columns"] + list(grid_columns))),
                              skipped=record["skipped"]))


def record_skip(dest_root: str, task: str, column: str, reason) -> None:
  """Notes in grid.json that the grid skipped the cell, with its one-line `reason`; None: it ran (no longer
  skipped)."""
  record = grid_record(dest_root)
  key = rundir.grid_cell(task, column)
  if reason is None and key not in record["skipped"]:
    return
  if reason is None:
    del record["skipped"][key]
  else:
    record["skipped"][key] = str(reason)
  _write_grid(dest_root, record)


def _write_grid(dest_root: str, record: Dict) -> None:
  os.makedirs(dest_root, exist_ok=True)
  fileio.atomic_write_json(os.path.join(dest_root, GRID_FILE), record)


def main(argv) -> int:
  """python -m roboshape.report.publish RUN_WORKDIR DEST_ROOT: `publish` of the run in RUN_WORKDIR (its config.json)."""
  if len(argv) != 3 or any(a.startswith("-") for a in argv[1:]):
    print("usage: python -m roboshape.report.publish RUN_WORKDIR DEST_ROOT   (e.g. results/small)", file=sys.stderr)
    return 2
  try:
    config = rundir.load_config(argv[1])
    if "grid" in config:
      raise UserError(f"{argv[1]} is a grid's workdir: publish each of its runs (<workdir>/<task>_<column>), or "
                      "let the grid publish them (--config.grid.publish).")
    dest = publish(config, argv[1], argv[2])
  except UserError as e:
    return errors.print_error(e)
  print(f"[roboshape] published {argv[1]} to {dest}", flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv))
