"""The pipeline's stages and the order a config runs them in.

Each stage is a module with `run(config, workdir)`; it is imported only when it runs, so a stage that renders never
imports TensorFlow and a stage that trains never imports SAPIEN. Each stage resumes where a killed run stopped
and skips work that is already done.
"""
import importlib
import json
import os
import time

from roboshape import encoders
from roboshape import fileio
from roboshape.cli import UserError

STAGE_MODULES = {
    "collect": "roboshape.data.collect",
    "pretrain": "",           # the encoder's own (roboshape.encoders.Kind.pretrain), e.g. roboshape.train.pretrain
    "cache": "roboshape.train.cache",
    "train_policy": "roboshape.train.bc",
    "evaluate": "roboshape.eval.closed_loop",
    "report": "roboshape.eval.report",
}


def save_config(config, workdir: str) -> str:
  """Writes config.json into the workdir (atomically) and returns its path."""
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, "config.json")
  fileio.atomic_write_text(path, config.to_json_best_effort(indent=2, sort_keys=True))
  return path


def load_config(workdir: str):
  """The config a run saved in its workdir, as a ConfigDict."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  path = os.path.join(workdir, "config.json")
  if not os.path.exists(path):
    raise UserError(f"{path} not found: is {workdir!r} the workdir of a `python launch.py` run?")
  with open(path) as f:
    return ml_collections.ConfigDict(json.load(f))


def grid_configs(config, workdir: str):
  """(task, encoder, config, workdir) of each run of a grid config, in the order the grid runs them.

  A grid config (configs/reproduce.py) is an experiment config plus `grid.tasks` and `grid.encoders`; each run
  is that config with its task and encoder set, in <workdir>/<task>_<encoder>/, reading the task's dataset from
  <workdir>/data/<task> (shared by the task's runs; collected once). Runs of encoders with a pretraining stage (SAVi) come first within a task.
  """
  import ml_collections  # pylint: disable=import-outside-toplevel
  base = config.to_dict()
  base.pop("grid")
  data_root = config.data.dir or os.path.join(workdir, "data")
  order = sorted(config.grid.encoders, key=lambda e: not encoders.get(e).pretrain)
  for task in config.grid.tasks:
    for encoder in order:
      sub = ml_collections.ConfigDict(base)
      sub.task, sub.encoder, sub.name = task, encoder, f"{task}_{encoder}"
      pretrains = encoders.get(encoder).pretrain
      sub.stages = tuple(s for s in config.stages if s != "report" and (pretrains or s != "pretrain"))
      sub.data.dir = os.path.join(data_root, task)
      yield task, encoder, sub, os.path.join(workdir, f"{task}_{encoder}")


def run_grid(config, workdir: str) -> None:
  """Runs every (task, encoder) of a grid config, then the report over all of them.

  A baseline (any encoder but SAVi) whose run raises `UserError` (e.g. its pretrained weights are absent) is
  recorded as skipped in <run>/SKIPPED.json, with the message as the reason, and the grid goes on; the report
  prints it as a "skipped: <reason>" line.
  """
  unknown = [s for s in config.stages if s not in STAGE_MODULES]
  if unknown:
    raise UserError(f"unknown stage(s) {', '.join(unknown)}; stages are {', '.join(STAGE_MODULES)}.")
  save_config(config, workdir)
  for task, encoder, sub, sub_dir in grid_configs(config, workdir):
    skipped = os.path.join(sub_dir, "SKIPPED.json")
    print(f"[roboshape] grid run {task} x {encoder} -> {sub_dir}", flush=True)
    try:
      run(sub, sub_dir)
    except UserError as e:
      if encoder == "savi":
        raise
      os.makedirs(sub_dir, exist_ok=True)
      with open(skipped, "w") as f:
        json.dump({"reason": str(e)}, f)
      print(f"[roboshape] skipped {task} x {encoder}: {e}", flush=True)
      continue
    if os.path.exists(skipped):
      os.remove(skipped)
  if "report" in config.stages:
    importlib.import_module(STAGE_MODULES["report"]).run(config, workdir)


def run(config, workdir: str) -> None:
  """Runs config.stages in order, each as `run(config, workdir)` of its module (a grid config: `run_grid`)."""
  if "grid" in config:
    run_grid(config, workdir)
    return
  unknown = [s for s in config.stages if s not in STAGE_MODULES]
  if unknown:
    raise UserError(f"unknown stage(s) {', '.join(unknown)}; stages are {', '.join(STAGE_MODULES)}.")
  save_config(config, workdir)
  for name in config.stages:
    module_name = encoders.get(config.encoder).pretrain if name == "pretrain" else STAGE_MODULES[name]
    if not module_name:
      raise UserError(f"the {config.encoder} encoder has no pretrain stage; drop it from --config.stages.")
    try:
      module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
      if e.name and e.name.startswith("roboshape"):
        raise UserError(f"stage {name!r} is not implemented in this version of roboshape "
                        f"({module_name} is missing); drop it with --config.stages.") from None
      raise
    print(f"[roboshape] stage {name} -> {workdir}", flush=True)
    start = time.time()
    module.run(config, workdir)
    print(f"[roboshape] stage {name} done in {time.time() - start:.1f}s", flush=True)
