"""Copies a finished run's results out of its workdir, so they survive the machine (e.g. into results/small/).

  publish(config, workdir, dest_root)  ->  <dest_root>/<task>_<column>/

The folder is named after the run's column (roboshape/encoders/columns.py): its encoder, with its options
("push_savi+proprio").

A grid config with `grid.publish` set (configs/reproduce.py:small: "results/small") publishes each run as soon as
its evaluation is complete. What is copied, under fixed names (files the run does not have are left out):

  config.json                      the config that ran
  stages.json                      each stage's wall time (roboshape.status reads it)
  results.csv, table.md, table.tex, success_by_level.png, milestones.md   eval/: every rollout, the tables, the
                                                                          plot, how far the rollouts got
  policy_val_metrics.json/.png     the policy's validation curve (with policy.train_seeds, one per seed s:
                                   policy_seed_<s>_val_metrics.json/.png)
  <encoder>_val_metrics.json/.png  the encoder's pretraining curve (savi, ae), and its seed selection files (from
                                   the run that pretrained it: pretrain.from_workdir)
  videos/*.mp4                     the rollout videos the evaluation recorded (a few per level)

Files of an earlier publication of the same run that this one does not replace are removed, so the folder always
holds one run; a README.md written there by hand is kept.
"""
import glob
import os
import shutil
from typing import List

from roboshape import rundir
from roboshape.encoders import columns
from roboshape.errors import UserError

KEPT = ("README.md",)
EVAL_FILES = (rundir.RESULTS_CSV, "table.md", "table.tex", "success_by_level.png", "milestones.md")


def planned(config, workdir: str) -> List[tuple]:
  """(source path, name in the published folder) of every file `publish` copies from `workdir` (and from the
  workdir whose pretrain stage trained its encoder)."""
  pairs = [(rundir.config_path(workdir), "config.json"), (rundir.stage_log_path(workdir), "stages.json")]
  pairs += [(os.path.join(rundir.eval_dir(workdir), name), name) for name in EVAL_FILES]
  for seed in rundir.train_seeds(config):
    policy, name = rundir.policy_dir(workdir, seed), "policy" if seed is None else f"policy_seed_{seed}"
    pairs += [(os.path.join(policy, f"val_metrics{ext}"), f"{name}_val_metrics{ext}") for ext in (".json", ".png")]
  encoder_dir = rundir.pretrain_dir(rundir.pretrained_workdir(config, workdir), config.encoder)
  for path in sorted(glob.glob(os.path.join(encoder_dir, "*.json")) + glob.glob(os.path.join(encoder_dir, "*.png"))):
    pairs.append((path, f"{config.encoder}_{os.path.basename(path)}"))
  for path in sorted(glob.glob(os.path.join(rundir.videos_dir(workdir), "*.mp4"))):
    pairs.append((path, os.path.join("videos", os.path.basename(path))))
  return [(src, name) for src, name in pairs if os.path.isfile(src)]


def publish(config, workdir: str, dest_root: str) -> str:
  """Copies the results of the run in `workdir` to <dest_root>/<task>_<column>/; returns that folder.

  Raises UserError when the run has no evaluation results yet (nothing is copied then)."""
  if not os.path.exists(os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_FILE)):
    raise UserError(f"{workdir} has no evaluation results ({rundir.RESULTS_FILE}) to publish: run its evaluate "
                    "stage first.")
  dest = os.path.join(dest_root, f"{config.task}_{columns.of_config(config)}")
  pairs = planned(config, workdir)
  names = {name for _, name in pairs}
  if os.path.isdir(dest):
    for folder, _, files in os.walk(dest):
      for name in files:
        rel = os.path.relpath(os.path.join(folder, name), dest)
        if rel not in names and rel not in KEPT:
          os.remove(os.path.join(folder, name))
  for src, name in pairs:
    target = os.path.join(dest, name)
    os.makedirs(os.path.dirname(target), exist_ok=True)
    shutil.copyfile(src, target + ".partial")
    os.replace(target + ".partial", target)
  return dest

