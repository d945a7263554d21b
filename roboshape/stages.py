"""The pipeline's stages and the order a config runs them in.

Each stage is a function of (config, workdir) in `STAGE_RUNS`, which imports its module only when it runs, so a stage
that renders never imports TensorFlow and a stage that trains never imports SAPIEN. Each stage resumes where a killed run stopped
and skips work that is already done. The pretrain stage is the encoder's own (roboshape.encoders.Kind.pretrain, a
key of `PRETRAINERS`), run with the validation of the encoder's evaluator (Kind.evaluator, a key of `EVALUATORS`,
in roboshape/eval/): this is where training meets evaluation, so that train/ never imports eval/.

A full disk ends a stage in one line (`DiskFull`, `disk_full_is_one_line`) wherever it is noticed, for every stage
alike: the stages write atomically (roboshape/fileio.py, orbax's temporary checkpoint folders, dataset shards under
temporary names), so what they wrote completely is kept and the same command resumes once there is space.
"""
import contextlib
import functools
import json
import os
import time
from typing import Sequence

import ml_collections

from roboshape import config_check
from roboshape import encoders
from roboshape import errors
from roboshape import fileio
from roboshape import lanes as lanes_lib
from roboshape import rundir
from roboshape.errors import DiskFull
from roboshape.errors import UserError
from roboshape.grid import grid_configs
from roboshape.grid import pretrained_from
from roboshape.train import fingerprint



def _collect(config, workdir: str) -> None:
  from roboshape.data import collect  # pylint: disable=import-outside-toplevel
  collect.run(config, workdir)


def _cache(config, workdir: str) -> None:
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  cache.run(config, workdir)


def _train_policy(config, workdir: str) -> None:
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  bc.run(config, workdir)


def _evaluate(config, workdir: str) -> None:
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  closed_loop.run(config, workdir)


def _report(config, workdir: str) -> None:
  from roboshape.report import report  # pylint: disable=import-outside-toplevel
  report.run(config, workdir)


def _pretrain_loop(config, workdir: str, make_validation) -> None:
  from roboshape.train import pretrain  # pylint: disable=import-outside-toplevel
  pretrain.run(config, workdir, make_validation)


def _check_policy(config) -> None:
  from roboshape.models import policy  # pylint: disable=import-outside-toplevel
  policy.check_config(config)


def _check_policy_training(config) -> None:
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  bc.check_config(config)


def _check_evaluation(config) -> None:
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  closed_loop.check_config(config)


def _check_pretraining(config) -> None:
  from roboshape.train import pretrain  # pylint: disable=import-outside-toplevel
  pretrain.check_config(config)


# The sections the stages' modules own, each checked by its owner's check_config with the rest of the config before
# any stage runs (roboshape/config_check.py); "pretrain" for the encoders that list it in Kind.sections.
SECTION_CHECKS = config_check.SectionChecks(
    every_run=(_check_policy, _check_policy_training, _check_evaluation),
    shared={"pretrain": _check_pretraining})


def check(config) -> None:
  """Raises UserError, one line naming the field and what to do, for the first problem of `config` (a run's or a
  grid's): roboshape.config_check.check with the stages' SECTION_CHECKS."""
  config_check.check(config, SECTION_CHECKS)


def _slots_validation(*args):
  from roboshape.eval import slots  # pylint: disable=import-outside-toplevel
  return slots.validation(*args)


def _reconstruction_validation(*args):
  from roboshape.eval import reconstruction  # pylint: disable=import-outside-toplevel
  return reconstruction.validation(*args)


# Every stage but pretrain: (config, workdir) -> None. Pretrain is the encoder's own: PRETRAINERS[Kind.pretrain]
# as (config, workdir, make_validation), given EVALUATORS[Kind.evaluator] (None for an encoder without one).
STAGE_RUNS = {
    "collect": _collect,
    "cache": _cache,
    "train_policy": _train_policy,
    "evaluate": _evaluate,
    "report": _report,
}
# Kind.pretrain -> the trainer: "loop", the pretraining loop (roboshape/train/pretrain.py), which trains Kind.model.
PRETRAINERS = {"loop": _pretrain_loop}
# Kind.evaluator -> its validation(config, root, model, episodes) (roboshape/eval/): SAVi's FG-ARI and per-object
# IoUs, the autoencoder's reconstruction error.
EVALUATORS = {"slots": _slots_validation, "reconstruction": _reconstruction_validation}


# The fields that make a workdir's config.json another run's: a run resumed or extended keeps them all.
_RUN_FIELDS = ("task", "encoder", "variant")


def _check_writable(workdir: str, flag: str = "--workdir") -> None:
  """Raises UserError unless `workdir` is a directory this process can write in, or can be created as one (a
  read-only file system fails here too: access(2) says EROFS to root as well). `flag` names the path's option."""
  if os.path.exists(workdir) and not os.path.isdir(workdir):
    raise UserError(f"{flag} {workdir} is a file, not a directory; give a directory (it is created if missing).")
  existing = os.path.abspath(workdir)
  while not os.path.exists(existing):
    existing = os.path.dirname(existing)
  if not os.path.isdir(existing):
    raise UserError(f"{flag} {workdir}: {existing} is a file, not a directory; give a path under a directory.")
  if not os.access(existing, os.W_OK | os.X_OK):
    raise UserError(f"{flag} {workdir} is not writable ({existing}: permission denied or a read-only file system); "
                    "give a directory you can write to.")


def _run_identity(config) -> dict:
  """What makes two configs the same run: a grid or one run, and task, encoder and variant (a grid: its variant,
  so a grid extended with more tasks or encoders is the same run)."""
  grid = "grid" in config
  fields = ("variant",) if grid else _RUN_FIELDS
  return dict({f: config[f] for f in fields if f in config}, kind="grid" if grid else "single run")


def _check_same_run(config, workdir: str) -> None:
  """Raises UserError when `workdir` already holds the config.json of another run (see `_run_identity`), or of a
  run today's code cannot resume (rundir.check_no_chunks)."""
  path = rundir.config_path(workdir)
  if not os.path.exists(path):
    return
  try:
    with open(path) as f:
      stored = json.load(f)
    if not isinstance(stored, dict):
      raise ValueError("not a JSON object")
  except (OSError, ValueError) as e:
    raise UserError(f"{path} is not a readable roboshape config.json ({e}); use another --workdir.") from None
  rundir.check_no_chunks(stored, workdir)
  mine, theirs = _run_identity(config), _run_identity(stored)
  differences = [f"{key}: {theirs[key]!r} in {path}, {mine[key]!r} in this config"
                 for key in mine if key in theirs and theirs[key] != mine[key]]
  if differences:
    raise UserError(f"workdir {workdir} holds a run of another config ({'; '.join(differences)}); use another "
                    "--workdir (nothing in it was changed).")


def check_workdir(config, workdir: str, redo: Sequence[str] = ()) -> fingerprint.Plan:
  """Raises UserError, before anything is written, unless `workdir` can hold the run of `config`: a directory
  (or a path where one can be made) this process can write in, without the config.json of another run, nor a
  stage's output made with other values of the fields it reads unless `redo` names that stage
  (roboshape/train/fingerprint.py). Returns the fingerprint plan the run carries out once it holds the workdir."""
  _check_writable(workdir)
  if "collect" in config.get("stages", ()) and config.get("data", {}).get("dir"):
    _check_writable(config.data.dir, "--config.data.dir")
  _check_same_run(config, workdir)
  return fingerprint.check(config, workdir, redo, _check_dataset(config, workdir))


def _check_dataset(config, workdir: str) -> list:
  """A run that collects must not find a dataset of another config where it would collect (the collect stage
  would refuse it, after config.json had been rewritten): one in a shared config.data.dir is refused here; the
  differences of one in the run's own data folder are returned, for `fingerprint.check` to refuse them or --redo
  to set that dataset aside. Imports the collect stage (TensorFlow) only when a dataset folder exists."""
  if "collect" not in config.stages or not os.path.isdir(rundir.data_root(config, workdir)):
    return []
  from roboshape.data import collect  # pylint: disable=import-outside-toplevel
  own = collect.own_dataset_differences(config, workdir)
  if not own:
    collect.check_existing(config, workdir)
  return own


def check_redo(config, redo: Sequence[str]) -> None:
  """Raises a one-line UserError unless every stage `redo` names (launch.py's --redo) is one whose output records
  what it was made with (fingerprint.RECORDED) and that the config runs: a stage set aside and not run again would
  leave the workdir without it. A shared dataset (config.data.dir, every grid's) is never set aside."""
  unknown = [s for s in redo if s not in fingerprint.RECORDED]
  if unknown:
    raise UserError(f"--redo={','.join(redo)}: {', '.join(unknown)} is not a stage --redo takes; it takes "
                    f"{', '.join(fingerprint.RECORDED)} (the cache, the evaluation and the report follow them by "
                    "themselves).")
  missing = [s for s in redo if s not in config.stages]
  if missing:
    raise UserError(f"--redo={','.join(redo)}: config.stages does not run {', '.join(missing)}, so its output "
                    "would be set aside and not made again: add it to --config.stages, or drop it from --redo.")
  if "collect" in redo and ("grid" in config or config.data.dir):
    raise UserError("--redo=collect sets aside only a dataset in the run's own workdir, and this run's is shared "
                    "(config.data.dir, or a grid's datasets): collect a new one into another --config.data.dir "
                    "instead.")


def run_grid(config, workdir: str, redo: Sequence[str] = ()) -> None:
  """Runs every (task, column) of a grid config, then the report over all of them.

  A baseline (any encoder but SAVi) whose run raises `UserError` (e.g. its pretrained weights are absent) is
  recorded as skipped in <run>/SKIPPED.json, with the message as the reason, and the grid goes on; the report
  prints it as a "skipped: <reason>" line. A baseline whose weight file is absent (Kind.available) is skipped so
  before the first run starts. Every run's config and workdir are checked before the first one starts.
  With `grid.publish` set, each run's results are copied there as soon as it is evaluated (roboshape/report/publish.py).
  With `grid.lanes` > 1 the task's datasets are collected first, one task at a time, then up to `grid.lanes` runs
  go at once, each a child process pinned to its share of the cores (roboshape/lanes.py, its log in <run>/log.txt);
  the last run left is resumed on every core. `redo` (launch.py's --redo) reaches every run that runs the stage.
  The grid holds its workdir for the whole grid, and each run its own (rundir.hold_workdir). The grid's stage log
  (<workdir>/stages.json, entry rundir.GRID_CLOCK) adds up the wall time of its attempts: how long the whole grid
  took, across restarts, which no run's own log can tell (`roboshape.status` prints it).
  """
  check(config)
  check_redo(config, redo)
  runs = list(grid_configs(config, workdir))
  check_workdir(config, workdir)
  for _, _, sub, sub_dir in runs:
    check_workdir(sub, sub_dir, _redo_of(sub, redo))
  with rundir.hold_workdir(workdir):
    with disk_full_is_one_line("the grid", workdir):
      rundir.save_config(config, workdir)
      if config.grid.get("publish"):
        from roboshape.report import publish  # pylint: disable=import-outside-toplevel
        publish.record_grid(config.grid.publish, dict.fromkeys(t for t, _, _, _ in runs),
                            dict.fromkeys(c for _, c, _, _ in runs))
      runs = _skip_unavailable(config, runs)
    with rundir.stage_clock(workdir, rundir.GRID_CLOCK):
      _run_grid_runs(config, runs, redo)
      if "report" in config.stages:
        with disk_full_is_one_line("the report stage", workdir):
          STAGE_RUNS["report"](config, workdir)


def _redo_of(sub, redo: Sequence[str]) -> tuple:
  """The stages of a grid's --redo that its run `sub` runs (one served another run's encoder has no pretrain)."""
  return tuple(s for s in redo if s in sub.stages)


def run_redone(config, workdir: str, redo: Sequence[str] = ()) -> None:
  """`run` with the stages of `redo` that `config` runs: a grid's run, in its lane or here."""
  run(config, workdir, _redo_of(config, redo))


def _run_grid_runs(config, runs, redo: Sequence[str] = ()) -> None:
  """The grid's runs, in `grid.lanes` parallel lanes or one after another here."""
  lanes = int(config.grid.get("lanes", 1))
  if lanes > 1:
    _run_lanes(config, runs, lanes, redo)
    return
  for task, column, sub, sub_dir in runs:
    print(f"[roboshape] grid run {task} x {column} -> {sub_dir}", flush=True)
    try:
      run_redone(sub, sub_dir, redo)
    except DiskFull:
      raise
    except UserError as e:
      _finish_run(config, task, column, sub, sub_dir, str(e))
      continue
    _finish_run(config, task, column, sub, sub_dir, None)


def _skip_unavailable(config, runs):
  """The runs left after each baseline whose encoder is not available here (Kind.available: its weight file is
  absent) is recorded as skipped, as a run that failed for that reason would be, before any run starts: the status
  and the report say so from the grid's start, and no run starts only to fail."""
  left = []
  for task, column, sub, sub_dir in runs:
    kind = encoders.get(sub.encoder)
    if kind.baseline and kind.available is not None:
      try:
        kind.available(sub)
      except UserError as e:
        _finish_run(config, task, column, sub, sub_dir, str(e))
        continue
    left.append((task, column, sub, sub_dir))
  return left


def _run_lanes(config, runs, lanes: int, redo: Sequence[str] = ()) -> None:
  """The grid's runs in `lanes` parallel lanes, after each task's dataset is collected here: each lane's child
  process calls `run` on its run's config, as this process would. A run that serves another run's pretrained
  encoder (pretrain.from_workdir) starts once that run has ended."""
  collected = set()
  for task, _, sub, sub_dir in runs:
    if task not in collected and "collect" in sub.stages:
      print(f"[roboshape] grid: the {task} dataset first, for its runs to share", flush=True)
      first = ml_collections.ConfigDict(sub.to_dict())
      first.stages = ("collect",)
      run(first, sub_dir)
    collected.add(task)
  by_dir = {sub_dir: (task, column, sub) for task, column, sub, sub_dir in runs}
  failed = []

  def on_done(job, code: int, line: str) -> None:
    task, column, sub = by_dir[job[2]]
    if code == 0:
      _finish_run(config, task, column, sub, job[2], None)
      return
    message = line.removeprefix(errors.PREFIX) if code == 2 else f"exit status {code}: {line}"
    if code == 2 and encoders.get(sub.encoder).baseline and not message.startswith(DiskFull.PREFIX):
      _finish_run(config, task, column, sub, job[2], message)
    else:
      failed.append(f"{task} x {column} ({message})")

  lanes_lib.run_parallel(functools.partial(run_redone, redo=tuple(redo)) if redo else run,
                         [(f"{task} x {column}", sub, sub_dir) for task, column, sub, sub_dir in runs],
                         lanes, on_done, after=pretrained_from(runs))
  if failed:
    raise UserError(f"grid runs failed: {'; '.join(failed)}; their logs are <run>/{lanes_lib.LOG_FILE}, and the "
                    "same command resumes them.")


def _finish_run(config, task: str, column: str, sub, sub_dir: str, error) -> None:
  """After a grid run: `error` (a UserError's message) skips a baseline (SKIPPED.json) and stops the grid for SAVi
  (Kind.baseline); a run that ended well loses an old SKIPPED.json and is published when the grid publishes (or
  says in a line why not, e.g. its task's published cells were trained on another dataset, and the grid goes on)."""
  from roboshape.report import publish  # pylint: disable=import-outside-toplevel
  dest = config.grid.get("publish")
  skipped = os.path.join(sub_dir, rundir.SKIPPED_FILE)
  if error is not None:
    if not encoders.get(sub.encoder).baseline:
      raise UserError(error)
    os.makedirs(sub_dir, exist_ok=True)
    fileio.atomic_write_json(skipped, {"reason": error})
    if dest:
      publish.record_skip(dest, task, column, error)
    print(f"[roboshape] skipped {task} x {column}: {error}", flush=True)
    return
  if os.path.exists(skipped):
    os.remove(skipped)
  if dest:
    publish.record_skip(dest, task, column, None)
  if dest and "evaluate" in sub.stages:
    try:
      print(f"[roboshape] published {task} x {column} to {publish.publish(sub, sub_dir, dest)}", flush=True)
    except UserError as e:      # e.g. its row in `dest` is on another dataset: the run stays in its workdir
      print(f"[roboshape] not published: {e}", flush=True)


def stage_runner(name: str, config):
  """The stage `name` of `config` as a function of the workdir: STAGE_RUNS[name]; for "pretrain" the encoder's
  trainer (PRETRAINERS[Kind.pretrain]) given its evaluator's validation (EVALUATORS[Kind.evaluator], None for an
  encoder without one)."""
  if name != "pretrain":
    return functools.partial(STAGE_RUNS[name], config)
  kind = encoders.get(config.encoder)
  trainer = PRETRAINERS[kind.pretrain]
  make_validation = EVALUATORS[kind.evaluator] if kind.evaluator else None
  return lambda workdir: trainer(config, workdir, make_validation)


def run(config, workdir: str, redo: Sequence[str] = ()) -> None:
  """Runs config.stages in order, each as `stage_runner(name, config)(workdir)` (a grid config: `run_grid`).

  Before any stage runs and before config.json is written, the whole config is checked (`check`)
  and so is the workdir (`check_workdir`): bad input is a UserError and leaves the workdir as it was, and so does a
  config that differs from what a stage's output in the workdir was made with, unless `redo` (launch.py's --redo)
  names that stage, whose output is then set aside (roboshape/train/fingerprint.py). The run holds the workdir
  (rundir.hold_workdir) from then to its end, so a second run on it stops in one line. Each stage that records
  the config fields it reads records them as it starts (fingerprint.record), so config.json and the outputs agree.
  """
  redo = tuple(dict.fromkeys(redo))
  if "grid" in config:
    run_grid(config, workdir, redo)
    return
  check(config)
  check_redo(config, redo)
  plan = check_workdir(config, workdir, redo)
  with rundir.hold_workdir(workdir):
    with disk_full_is_one_line("the run", workdir):
      fingerprint.apply(plan, workdir, config)
      rundir.save_config(config, workdir)
    for name in config.stages:
      runner = stage_runner(name, config)
      print(f"[roboshape] stage {name} -> {workdir}", flush=True)
      start = time.time()
      with disk_full_is_one_line(f"the {name} stage", workdir):
        with rundir.stage_clock(workdir, name):
          fingerprint.record(config, workdir, name)
          runner(workdir)
      print(f"[roboshape] stage {name} done in {time.time() - start:.1f}s", flush=True)


@contextlib.contextmanager
def disk_full_is_one_line(what: str, workdir: str):
  """Turns a full disk met inside (an OSError(ENOSPC), or a library's error that says so, raised here or by a
  background writer at its next call: fileio.disk_full) into one `DiskFull` line: what stopped, the path it could
  not write (else the workdir), and the safe action. A UserError passes as it is (collect's says more)."""
  try:
    yield
  except UserError:
    raise
  except Exception as e:  # pylint: disable=broad-except
    if not fileio.disk_full(e):
      raise
    raise DiskFull(f"{DiskFull.PREFIX} while {what} wrote {fileio.disk_full_path(e) or workdir}: what it wrote "
                   f"completely is kept. Free some space on that disk (keep {workdir}: the run resumes from it) "
                   "and run the same command again to resume.") from e
