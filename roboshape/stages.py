"""The pipeline's stages and the order a config runs them in.

Each stage is a module with `run(config, workdir)`; it is imported only when it runs, so a stage that renders never
imports TensorFlow and a stage that trains never imports SAPIEN. Each stage resumes where a killed run stopped
and skips work that is already done.
"""
import importlib
import json
import os
import time

from roboshape.cli import UserError

STAGE_MODULES = {
    "collect": "roboshape.data.collect",
    "pretrain": "roboshape.train.pretrain",
    "cache": "roboshape.train.cache",
    "train_policy": "roboshape.train.bc",
    "evaluate": "roboshape.eval.closed_loop",
    "report": "roboshape.eval.report",
}


def save_config(config, workdir: str) -> str:
  """Writes config.json into the workdir (atomically) and returns its path."""
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, "config.json")
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    f.write(config.to_json_best_effort(indent=2, sort_keys=True))
  os.replace(tmp, path)
  return path


def load_config(workdir: str):
  """The config a run saved in its workdir, as a ConfigDict."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  path = os.path.join(workdir, "config.json")
  if not os.path.exists(path):
    raise UserError(f"{path} not found: is {workdir!r} the workdir of a `python launch.py` run?")
  with open(path) as f:
    return ml_collections.ConfigDict(json.load(f))


def run(config, workdir: str) -> None:
  """Runs config.stages in order, each as `run(config, workdir)` of its module."""
  unknown = [s for s in config.stages if s not in STAGE_MODULES]
  if unknown:
    raise UserError(f"unknown stage(s) {', '.join(unknown)}; stages are {', '.join(STAGE_MODULES)}.")
  save_config(config, workdir)
  for name in config.stages:
    try:
      module = importlib.import_module(STAGE_MODULES[name])
    except ModuleNotFoundError as e:
      if e.name and e.name.startswith("roboshape"):
        raise UserError(f"stage {name!r} is not implemented in this version of roboshape "
                        f"({STAGE_MODULES[name]} is missing); drop it with --config.stages.") from None
      raise
    print(f"[roboshape] stage {name} -> {workdir}", flush=True)
    start = time.time()
    module.run(config, workdir)
    print(f"[roboshape] stage {name} done in {time.time() - start:.1f}s", flush=True)
