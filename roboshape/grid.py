"""The runs of a grid config (configs/reproduce.py): an experiment config plus `grid.tasks` and `grid.encoders`.

  for task, encoder, sub_config, sub_workdir in grid_configs(config, workdir): ...

roboshape/stages.py runs them (then the report over all of them); roboshape/config_check.py checks each of them
before the first one starts.
"""
from roboshape import encoders
from roboshape import rundir


def grid_configs(config, workdir: str):
  """(task, encoder, config, workdir) of each run of a grid config, in the order the grid runs them.

  Each run is the grid's config with its task and encoder set, in rundir.grid_run_dir (<workdir>/<task>_<encoder>/),
  reading the task's dataset from rundir.grid_data_dir (<data_root>/<task>, shared by the task's runs; collected
  once). Runs of encoders with a pretraining stage (SAVi) come first within a task. `grid.train_seeds`, a
  {task: seeds} mapping, sets policy.train_seeds for the runs of the tasks it names; `grid.task_control`, a
  {task: {field: value}} mapping, updates policy.eval for them (how that task's policies are run at control time);
  `grid.task_train`, the same for policy.train (how long that task's policies are trained).
  """
  import ml_collections  # pylint: disable=import-outside-toplevel
  base = config.to_dict()
  base.pop("grid")
  order = sorted(config.grid.encoders, key=lambda e: not encoders.get(e).pretrain)
  for task in config.grid.tasks:
    for encoder in order:
      sub = ml_collections.ConfigDict(base)
      sub.task, sub.encoder, sub.name = task, encoder, f"{task}_{encoder}"
      pretrains = encoders.get(encoder).pretrain
      sub.stages = tuple(s for s in config.stages if s != "report" and (pretrains or s != "pretrain"))
      sub.data.dir = rundir.grid_data_dir(config, workdir, task)
      seeds = config.grid.get("train_seeds", {}).get(task)
      if seeds:
        sub.policy.train_seeds = tuple(seeds)
      control = config.grid.get("task_control", {}).get(task)
      if control:
        sub.policy.eval.update(control.to_dict())
      train = config.grid.get("task_train", {}).get(task)
      if train:
        sub.policy.train.update(train.to_dict())
      yield task, encoder, sub, rundir.grid_run_dir(workdir, task, encoder)
