"""The paper's experiments in one command: collect -> pretrain -> cache -> train_policy -> evaluate for every
(task, column) of a grid, then one report over all of them.

Command:  python launch.py --config=configs/reproduce.py[:tiny|small|paper] --workdir=runs/reproduce_<variant>
          (`make demo` runs the :tiny variant into runs/demo)
Runtime:  results/small/README.md for :small (from the published cells' stage logs); benchmarks/gpu_scaleup.py
          projects :paper's.
Results:  results/small/README.md (one folder per cell, results/small/<task>_<column>/README.md)

Variants:
  tiny:  push x SAVi at the tiny scale (4 demos, 20 training steps, 1 seed x 2 rollouts per level): checks the
         whole pipeline end to end; its success rates mean nothing (20 training steps).
  small: {push, pick, place} x {SAVi, AE, Objects, State, R3M, DINO, SAVi+proprio, AE+proprio} at the small scale
         (2000 demos, 3 evaluation seeds x 20 rollouts per level), three training seeds per cell on every task and
         three pretraining seeds for SAVi and the AE, each selected by its own validation metric. The +proprio
         columns are SAVi and the AE with policy.proprio=True (the robot's pose as one more token per frame, the
         option beyond the paper that the recipe study keeps: results/small/recipe/README.md; the columns:
         roboshape/encoders/columns.py); each serves the SAVi or AE its task's plain column pretrained
         (pretrain.from_workdir) and starts once that run has ended. Resumable run by run on the machine that holds the
         workdir (a dataset collected again on another machine may differ in its bytes, and the report takes a
         task's cells from one dataset: results/small/README.md). Each run's results are copied to
         results/small/<task>_<column>/ as soon as it is evaluated (grid.publish), so the table survives the
         machine; `python -m roboshape.status <workdir>` says which runs are done, running or pending, how
         long each stage took and roughly how many core-hours are left. Two runs at once (grid.lanes=2), each
         pinned to one core, each logging to <run>/log.txt. Baselines whose weights are absent
         (config.baselines.*.path) are skipped when the grid starts, said in the report. One task's row alone:
         --config.grid.tasks="('push',)" (with --config.grid.train_seeds.push="()"
         --config.pretrain.train_seeds="(0,)" for one training seed and one SAVi seed). Cells published from
         another workdir on the same dataset are left out with --config.grid.skip="('place_savi', 'place_ae')".
  paper: {push, pick, place} x {SAVi, R3M, DINO}, 2000 demos per task, 3 seeds x 100 rollouts per level.

Layout: <workdir>/data/<task>/ (one dataset per task, shared by its runs), <workdir>/<task>_<column>/ (one run:
savi/, features/, policy/, eval/, dataset.json: its dataset's identity), <workdir>/report/report.md (tables per task
+ overall figure).
Any field can be overridden, e.g. --config.grid.tasks="('pick',)" --config.eval.rollouts_per_seed=50.
"""
import ml_collections

from configs import common

GRIDS = {
    "tiny": (("push",), ("savi",)),
    "small": (common.TASKS, ("savi", "ae", "objects", "state", "r3m", "dino", "savi+proprio", "ae+proprio")),
    "paper": (common.TASKS, ("savi", "r3m", "dino")),
}


def get_config(variant: str = "paper"):
  variant = variant or "paper"
  if variant not in GRIDS:
    raise ValueError(f"unknown variant {variant!r}; use configs/reproduce.py:<variant> with one of "
                     f"{', '.join(GRIDS)}.")
  tasks, encoders = GRIDS[variant]
  config = common.get_config(tasks[0], encoders[0], variant)
  config.name = f"reproduce_{variant}"
  config.stages = common.STAGES
  if variant == "small":
    # SAVi and the AE (the pretrain section is theirs alike) trained from 3 seeds, the best validation FG-ARI (AE:
    # reconstruction MSE) kept: object-centric models vary much between seeds (results/savi_small)
    config.pretrain.train_seeds = (0, 1, 2)
  config.grid = ml_collections.ConfigDict(dict(
      tasks=tasks, encoders=encoders,
      publish="results/small" if variant == "small" else "",   # where each evaluated run's results are copied
      # cells ("<task>_<column>") the grid does not run, e.g. cells published from another workdir on the same dataset
      skip=(),
      # runs at once, each a child process pinned to its share of the cores: two on the 2-core CPU machine (why:
      # roboshape/lanes.py)
      lanes=2 if variant == "small" else 1,
      # {task: policy.train_seeds} for the runs of that task: three training seeds per run, as the paper repeats
      # each experiment 3 times (they triple the behaviour cloning's and the evaluation's time)
      train_seeds=ml_collections.ConfigDict(
          {t: (0, 1, 2) for t in tasks} if variant in ("small", "paper") else {}),
      # {task: policy.eval settings} for the runs of that task: how its policies are run at control time where it
      # differs from the defaults (common.TASK_CONTROL; the config above was built for the first task only)
      task_control=ml_collections.ConfigDict({t: common.TASK_CONTROL[t] for t in tasks if t in common.TASK_CONTROL}),
      # {task: policy.train settings} for the runs of that task (common.TASK_TRAIN; common.TASK_SMALL_STEPS at :small)
      task_train=ml_collections.ConfigDict(_task_train(tasks, variant)),
  ))
  return config


def _task_train(tasks, variant: str) -> dict:
  """{task: the policy.train fields common.get_config sets per task} over `tasks`: every field some task sets, at
  each task's own value (the default where it sets none), so no run inherits the first task's."""
  default = common.policy_config(variant).train
  per_task = {t: dict(common.TASK_TRAIN.get(t, {})) for t in tasks}
  if variant == "small":
    for t in tasks:
      if t in common.TASK_SMALL_STEPS:
        per_task[t]["steps"] = common.TASK_SMALL_STEPS[t]
  keys = sorted({k for f in per_task.values() for k in f})
  return {t: {k: per_task[t].get(k, default[k]) for k in keys} for t in tasks} if keys else {}
