"""One check of a whole experiment config before any stage runs: bad values fail in seconds, not hours later.

  stages.check(config)     # config_check.check(config, stages.SECTION_CHECKS): roboshape.errors.UserError naming
                           # the first bad field and what to do

Every stage used to check its own fields when it started, so a bad `eval.levels` failed after collect, pretrain,
cache and train_policy had run. `check` covers the fields of every stage up front: types and ranges (counts are
ints >= 1, or >= 0 where 0 means something), learning rates > 0, probabilities in [0, 1], choices among known
values (task, encoder, stages, levels, ...), and the constraints between fields (policy.eval.history <=
policy.history, env.min_distractors <= env.max_distractors, pretrain.train.depth_weight > 0 needs env.depth, SAVi's
decoder size vs the frames it models, ...). It reports the FIRST problem found, in one line, as
"<field>=<value>: use ...". A grid config (configs/reproduce.py) is checked as each of its runs.

Each range is declared once, as roboshape/ranges.py data, beside what owns the field: here those of the sections
every run reads that no stage owns (run, env, data, sim); in the module that reads them those of the stages'
sections (the policy trunk's in roboshape/models/policy.py, its training's in roboshape/train/bc.py, the
evaluation's in roboshape/eval/closed_loop.py, the pretraining loop's in roboshape/train/pretrain.py), which
roboshape/stages.py hands in as a SectionChecks, so this module imports nothing from models, train or eval; with its
registration those of an encoder's own sections (roboshape/encoders: Kind.sections, checked by Kind.check), which
are checked for that encoder alone, so a value only another encoder needs (e.g. SAVi's decoder for
env.resolution=32) never refuses an R3M run. Checks that depend on the machine or on files (the device count,
checkpoints, datasets) stay in the stages. Importing this module is cheap; an encoder's check imports its model
modules (JAX, Flax) only for that encoder, and never starts a JAX backend. Defaults are configs/common.py's alone:
every field checked here is required.
"""
import dataclasses
import os
from typing import Any, Callable, Mapping, Tuple

from roboshape import encoders
from roboshape import envs
from roboshape.envs import camera
from roboshape import ranges
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.errors import UserError
from roboshape.sim import spec as spec_lib

Int, Number, Flag = ranges.Int, ranges.Number, ranges.Flag

# The ranges of the sections every run reads that no stage owns (the stages' own: SectionChecks).
_RANGES = {
    "run": (
        Int("seed", 0, "the seed of initialisation, data order and sampling"),
    ),
    "env": (
        Flag("env.depth", "also store the camera's depth"),
    ),
    "data": (
        Int("data.train_episodes", 1, "successful expert demos to collect for training"),
        Int("data.min_val_episodes", 1, "the fewest validation demos; pretrain and train_policy validate on them"),
        Number("data.val_fraction", 0.0, "validation demos per training demo", high=1.0),
    ),
    "sim": (
        Int("sim.num_workers", 0, "simulator worker processes; 0: one per CPU core"),
        Number("sim.step_timeout", 0.0, "seconds a worker may take for one reset or step", low_ok=False),
        Number("sim.episode_timeout", 0.0, "seconds a worker may take for one expert episode", low_ok=False),
    ),
}


# ----------------------------------------------------------------------------------------------------------------
# The sections.


def _check_stages(config) -> Tuple[str, ...]:
  """config.stages: a tuple of known stage names (rundir.STAGES)."""
  names = ranges.value(config, "stages")
  if isinstance(names, str) or not isinstance(names, (tuple, list)):
    raise UserError(f"stages={names!r}: use a tuple of stages, e.g. \"('collect', 'pretrain')\", of "
                    f"{ranges.choices(rundir.STAGES)}.")
  unknown = [s for s in names if s not in rundir.STAGES]
  if unknown:
    raise UserError(f"unknown stage(s) {ranges.choices(unknown)} in stages; use some of "
                    f"{ranges.choices(rundir.STAGES)}.")
  return tuple(names)


def _check_run(config) -> encoders.Kind:
  """task, encoder, stages and seed: known names, a pretrain stage only for an encoder that has one. Returns the
  encoder's registration."""
  ranges.Choice("task", envs.TASKS, "the task").check(config)
  kind = encoders.get(ranges.Choice("encoder", encoders.names(),
                                    "a registered encoder; add one as a module in roboshape/encoders/").check(config))
  stages = _check_stages(config)
  if "pretrain" in stages and not kind.pretrain:
    raise UserError(f"the {kind.name} encoder has no pretrain stage; drop it from --config.stages.")
  ranges.check(config, _RANGES["run"])
  _check_pretrained_elsewhere(config, kind, stages)
  return kind


def _check_pretrained_elsewhere(config, kind: encoders.Kind, stages: Tuple[str, ...]) -> None:
  """pretrain.from_workdir: "" or the workdir of another run, for an encoder with a pretrain stage, in a run that
  does not pretrain it itself."""
  source = ranges.value(config, "pretrain.from_workdir")
  if not isinstance(source, str):
    raise UserError(f"pretrain.from_workdir={source!r}: use the workdir of the run that pretrained the encoder, or "
                    "\"\" to pretrain it in this run's workdir.")
  if source and not kind.pretrain:
    raise UserError(f"pretrain.from_workdir={source!r}: the {kind.name} encoder has no pretrain stage to take from "
                    "another run; set pretrain.from_workdir=\"\".")
  if source and "pretrain" in stages:
    raise UserError(f"pretrain.from_workdir={source!r} serves the {kind.title} pretrained there, and stages trains "
                    "one here: drop 'pretrain' from --config.stages, or set pretrain.from_workdir=\"\".")


def _check_env(config) -> None:
  """The env section, by the simulator bridge's own EnvSpec (distractors, horizon, backend)."""
  resolution = ranges.value(config, "env.resolution")
  if not ranges.is_int(resolution) or not envs.MIN_RESOLUTION <= resolution <= envs.MAX_RESOLUTION:
    raise UserError(f"env.resolution={resolution!r}: use an int in [{envs.MIN_RESOLUTION}, {envs.MAX_RESOLUTION}] "
                    "(the camera's side in pixels; 64 by default).")
  spec_lib.EnvSpec.from_config(config)
  ranges.check(config, _RANGES["env"])


def _check_grid(config) -> None:
  """grid.tasks: a non-empty tuple of known tasks; grid.encoders: of distinct columns, each a registered encoder
  alone or with options (roboshape/encoders/columns.py); grid.skip: cells of these; grid.publish a folder."""
  tasks = ranges.value(config, "grid.tasks")
  if isinstance(tasks, str) or not isinstance(tasks, (tuple, list)) or not tasks or any(
      t not in envs.TASKS for t in tasks):
    raise UserError(f"grid.tasks={tasks!r}: use a non-empty tuple of {ranges.choices(envs.TASKS)}.")
  names = ranges.value(config, "grid.encoders")
  if isinstance(names, str) or not isinstance(names, (tuple, list)) or not names or len(set(names)) != len(names):
    raise UserError(f"grid.encoders={names!r}: use a non-empty tuple of distinct columns, each a registered encoder "
                    f"({ranges.choices(encoders.names())}) alone or with options, e.g. ('savi', 'savi+proprio').")
  for name in names:
    try:
      columns.parse(name)
    except UserError as e:
      raise UserError(f"grid.encoders={names!r}: {e}") from None
  skip = ranges.value(config, "grid.skip") if "skip" in config.grid else ()
  cells = {rundir.grid_cell(t, c) for t in tasks for c in names}
  if isinstance(skip, str) or not isinstance(skip, (tuple, list)) or any(s not in cells for s in skip):
    raise UserError(f"grid.skip={skip!r}: use a tuple of this grid's cells, \"<task>_<column>\" with a task of "
                    f"grid.tasks and a column of grid.encoders (e.g. ('place_savi',)), or () to run them all.")
  unknown = [t for t in config.grid.get("train_seeds", {}) if t not in envs.TASKS]
  if unknown:
    raise UserError(f"grid.train_seeds names {', '.join(map(repr, unknown))}: use tasks among "
                    f"{ranges.choices(envs.TASKS)}.")
  publish = config.grid.get("publish", "")
  if not isinstance(publish, str):
    raise UserError(f"grid.publish={publish!r}: use a folder (e.g. \"results/small\") or \"\" to publish nothing.")
  if publish and os.path.exists(publish) and not os.path.isdir(publish):
    raise UserError(f"grid.publish={publish!r} is a file; give a folder for the finished runs' results.")
  if "lanes" in config.grid:
    Int("grid.lanes", 1, "runs at once, each pinned to its share of the CPU cores (roboshape/lanes.py)").check(config)


@dataclasses.dataclass(frozen=True)
class SectionChecks:
  """The checks of the sections that the stages' own modules read, each declared by its owner (e.g. the policy
  trunk's ranges in roboshape/models/policy.py, the evaluation plan's in roboshape/eval/closed_loop.py) and handed
  in by the stages (roboshape/stages.py SECTION_CHECKS), so that this module imports none of them.

  every_run: checks of sections every run reads, in order; shared: section -> check, for the sections an encoder
  lists in Kind.sections (e.g. "pretrain", the pretraining loop's, for every encoder with a pretrain stage).
  """
  every_run: Tuple[Callable[[Any], None], ...]
  shared: Mapping[str, Callable[[Any], None]]


def check_single(config, sections: SectionChecks) -> None:
  """Raises UserError for the first field of a one-run config (no `grid`) that its stages cannot run with: the
  sections every run reads (here, then `sections.every_run`), then those of its encoder (Kind.sections: the shared
  ones of `sections`, then Kind.check)."""
  kind = _check_run(config)
  _check_env(config)
  ranges.check(config, _RANGES["data"] + _RANGES["sim"])
  for section_check in sections.every_run:
    section_check(config)
  for section in kind.sections:
    if section in sections.shared:
      sections.shared[section](config)
  if kind.check is not None:
    kind.check(config)
  _check_hand_relative(config, kind)
  _check_views(config, kind)


def _check_views(config, kind: encoders.Kind) -> None:
  """Several env.cameras need an encoder that reads every view with one set of weights (Kind.views), unless it
  reads no camera's frames at all (the state)."""
  cameras = tuple(config.env.cameras)
  if len(cameras) == 1 or kind.views or not any(k in camera.FRAME_KEYS for k in kind.inputs):
    return
  raise UserError(f"env.cameras={cameras!r}: the {kind.name} encoder reads the front view alone; use "
                  "env.cameras=('front',) with it, or an encoder that reads every view "
                  f"({', '.join(n for n in encoders.names() if encoders.get(n).views)}).")


def _check_hand_relative(config, kind: encoders.Kind) -> None:
  """policy.hand_relative needs the hand's pose (policy.proprio) and an encoder whose tokens say where their objects
  are (Kind.points)."""
  if not config.policy.hand_relative:
    return
  if not config.policy.proprio:
    raise UserError("policy.hand_relative=True needs the tool centre point: set policy.proprio=True too.")
  why = kind.points(config) if kind.points else f"the {kind.name} encoder's tokens do not say where their objects are"
  if why:
    raise UserError(f"policy.hand_relative=True: {why}; or leave policy.hand_relative False.")


def check(config, sections: SectionChecks) -> None:
  """Raises UserError, one line naming the field and what to do, for the first problem of `config`, with the
  stages' section checks `sections` (roboshape.stages.check passes them).

  A grid config (a `grid` field, configs/reproduce.py) is checked as its grid fields, then as each of its runs
  (roboshape.grid.grid_configs).
  """
  if "grid" not in config:
    check_single(config, sections)
    return
  from roboshape import grid  # pylint: disable=import-outside-toplevel
  _check_grid(config)
  _check_stages(config)
  for _, column, sub, _ in grid.grid_configs(config, ""):
    check_single(sub, sections)
    _check_column(sub, column)


def _check_column(sub, column: str) -> None:
  """A grid run is the column it is named after (roboshape/encoders/columns.py): an option's field set on the whole
  grid would make its plain columns another column's runs, under the plain column's name."""
  actual = columns.of_config(sub)
  if actual != column:
    extra = [f"--config.{f}={v!r}" for f, v in columns.parse(actual)[1].items()
             if f not in columns.parse(column)[1]]
    raise UserError(f"{' '.join(extra)} turns an option on for every column of the grid, so its {column!r} runs "
                    f"would be {actual!r}: leave it unset and add the columns that want it to grid.encoders "
                    f"(e.g. '{actual}').")
