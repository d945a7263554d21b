"""The runs of a grid config (configs/reproduce.py): an experiment config plus `grid.tasks` and `grid.encoders`.

  for task, column, sub_config, sub_workdir in grid_configs(config, workdir): ...

`grid.encoders` names columns: a registered encoder ("savi"), or one with options beyond the paper
("savi+proprio"; roboshape/encoders/columns.py says which fields each option sets). roboshape/stages.py runs them
(then the report over all of them); roboshape/config_check.py checks each of them before the first one starts.
"""
from roboshape import encoders
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.envs import camera


def grid_configs(config, workdir: str):
  """(task, column, config, workdir) of each run of a grid config, in the order the grid runs them.

  Each run is the grid's config with its task set and its column's encoder and option fields (columns.apply), in
  rundir.grid_run_dir (<workdir>/<task>_<column>/), reading the task's dataset from rundir.grid_data_dir
  (<data_root>/<task>, shared by the task's runs; collected once). The plain columns of every task come first, task
  by task (the paper's table: a grid stopped part way has its cells before any column beyond it), within a task
  those of encoders with a pretraining stage (SAVi, AE) first; then the columns with options, task by task. A column whose
  options set policy fields alone (columns.policy_only) serves the encoder its plain column's run pretrained when
  the grid has that column (pretrain.from_workdir, and no pretrain stage of its own): the policy fields change
  nothing pretraining reads, so the two runs would pretrain the same model. `pretrained_from` gives these pairs.
  `grid.skip` names cells (rundir.grid_cell) the grid does not run, e.g. cells published from another workdir on the
  same dataset; a column with options whose plain column is skipped pretrains its own encoder. `grid.train_seeds`, a
  {task: seeds} mapping, sets policy.train_seeds for the runs of the tasks it names;
  `grid.task_control`, a {task: {field: value}} mapping, updates policy.eval for them (how that task's policies are
  run at control time); `grid.task_train`, the same for policy.train (how long that task's policies are trained).
  """
  import ml_collections  # pylint: disable=import-outside-toplevel
  base = config.to_dict()
  base.pop("grid")
  names = tuple(config.grid.encoders)
  skip = set(config.grid.get("skip", ()))

  def order(column):
    encoder = columns.parse(column)[0]
    return not encoders.get(encoder).pretrain

  plain = sorted((c for c in names if columns.parse(c)[0] == c), key=order)
  for task, column in [(t, c) for t in config.grid.tasks for c in plain] + [
      (t, c) for t in config.grid.tasks for c in sorted((c for c in names if c not in plain), key=order)]:
    if rundir.grid_cell(task, column) in skip:
      continue
    sub = ml_collections.ConfigDict(base)
    sub.task, sub.name = task, rundir.grid_cell(task, column)
    columns.apply(sub, column)
    pretrains = encoders.get(sub.encoder).pretrain
    if (pretrains and sub.encoder in names and rundir.grid_cell(task, sub.encoder) not in skip
        and column != sub.encoder and columns.policy_only(column)):
      sub.pretrain.from_workdir = rundir.grid_run_dir(workdir, task, sub.encoder)
      pretrains = False
    sub.stages = tuple(s for s in config.stages if s != "report" and (pretrains or s != "pretrain"))
    sub.data.dir = rundir.grid_data_dir(config, workdir, task, camera.others(sub.env.cameras))
    seeds = config.grid.get("train_seeds", {}).get(task)
    if seeds:
      sub.policy.train_seeds = tuple(seeds)
    control = config.grid.get("task_control", {}).get(task)
    if control:
      sub.policy.eval.update(control.to_dict())
    train = config.grid.get("task_train", {}).get(task)
    if train:
      sub.policy.train.update(train.to_dict())
    yield task, column, sub, rundir.grid_run_dir(workdir, task, column)


def pretrained_from(runs) -> dict:
  """{run workdir: the workdir of the run whose pretrained encoder it serves} over `grid_configs`' runs: the runs
  that must wait for another run to end (roboshape/lanes.py)."""
  return {sub_dir: sub.pretrain.from_workdir for _, _, sub, sub_dir in runs if sub.pretrain.get("from_workdir")}
