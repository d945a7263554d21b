"""The run folder: where each stage of a run writes, and the config it ran with. Every module asks here.

  <workdir>/config.json      the config that ran (`save_config`, `load_config`)
  <workdir>/data/            the datasets (`data_root`: config.data.dir when set), one per task
  <workdir>/savi/            SAVi: checkpoints/, tb/, figures/, val_metrics.json/.png       (`savi_dir`)
  <workdir>/ae/              the `ae` encoder, as savi/                                      (`ae_dir`)
  <workdir>/features/<key>/  encoder features cached per (dataset, encoder checkpoint)       (`features_dir`)
  <workdir>/policy/          checkpoints/, tb/, norm_stats.json, encoder.json, summary.json   (`policy_dir`)
  <workdir>/eval/            results.jsonl/.json/.csv, tables, plots, videos/                 (`eval_dir`)
  <workdir>/report/          the report over a grid's runs (or the run itself)                (`report_dir`)

A grid config (configs/reproduce.py) runs each (task, encoder) in <workdir>/<task>_<encoder>/ (`grid_run_dir`),
reading the task's dataset from <data_root>/<task>; a grid run skipped for bad input leaves SKIPPED.json there.
`STAGES` names the stages, in the order a config runs them.
"""
import json
import os

from roboshape import fileio
from roboshape.errors import UserError

STAGES = ("collect", "pretrain", "cache", "train_policy", "evaluate", "report")
CONFIG_FILE = "config.json"
SKIPPED_FILE = "SKIPPED.json"      # a grid run skipped for bad input: {"reason": the one-line message}
CHECKPOINTS = "checkpoints"
RESULTS_FILE = "results.json"      # <eval_dir>/results.json: every rollout and the per-level summary


def config_path(workdir: str) -> str:
  return os.path.join(workdir, CONFIG_FILE)


def save_config(config, workdir: str) -> str:
  """Writes config.json into the workdir (atomically) and returns its path."""
  path = config_path(workdir)
  try:
    os.makedirs(workdir, exist_ok=True)
    fileio.atomic_write_text(path, config.to_json_best_effort(indent=2, sort_keys=True))
  except OSError as e:
    raise UserError(f"cannot write {path} ({e.strerror or e}); give a --workdir you can write to.") from None
  return path


def load_config(workdir: str):
  """The config a run saved in its workdir, as a ConfigDict."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  path = config_path(workdir)
  if not os.path.exists(path):
    raise UserError(f"{path} not found: is {workdir!r} the workdir of a `python launch.py` run?")
  with open(path) as f:
    return ml_collections.ConfigDict(json.load(f))


def data_root(config, workdir: str) -> str:
  """The folder that holds the datasets of a run: config.data.dir, or <workdir>/data when it is empty."""
  return config.data.dir or os.path.join(workdir, "data")


def savi_dir(workdir: str) -> str:
  return os.path.join(workdir, "savi")


def ae_dir(workdir: str) -> str:
  return os.path.join(workdir, "ae")


def features_dir(workdir: str, key: str) -> str:
  """The feature cache of one (encoder, dataset, dtype), named by its key (roboshape/train/cache.py)."""
  return os.path.join(workdir, "features", key)


def policy_dir(workdir: str) -> str:
  return os.path.join(workdir, "policy")


def eval_dir(workdir: str) -> str:
  return os.path.join(workdir, "eval")


def videos_dir(workdir: str) -> str:
  return os.path.join(eval_dir(workdir), "videos")


def report_dir(workdir: str) -> str:
  return os.path.join(workdir, "report")


def checkpoints(stage_dir: str) -> str:
  """The orbax checkpoints of a training stage's folder (savi_dir, ae_dir, policy_dir)."""
  return os.path.join(stage_dir, CHECKPOINTS)


def grid_run_dir(workdir: str, task: str, encoder: str) -> str:
  """The workdir of one run of a grid."""
  return os.path.join(workdir, f"{task}_{encoder}")


def grid_data_dir(config, workdir: str, task: str) -> str:
  """The data.dir of a grid's runs of `task`: the task's datasets, shared by its runs and collected once."""
  return os.path.join(data_root(config, workdir), task)
