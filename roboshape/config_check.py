"""One check of a whole experiment config before any stage runs: bad values fail in seconds, not hours later.

  config_check.check(config)     # raises roboshape.errors.UserError naming the first bad field and what to do

Every stage used to check its own fields when it started, so a bad `eval.levels` failed after collect, pretrain,
cache and train_policy had run. `check` covers the fields of every stage up front: types and ranges (counts are
ints >= 1, or >= 0 where 0 means something), learning rates > 0, probabilities in [0, 1], choices among known
values (task, encoder, stages, levels, ...), and the constraints between fields (policy.eval.history <=
policy.history, env.min_distractors <= env.max_distractors, pretrain.train.depth_weight > 0 needs env.depth, SAVi's
decoder size vs the frames it models, ...). It reports the FIRST problem found, in one line, as
"<field>=<value>: use ...". A grid config (configs/reproduce.py) is checked as each of its runs.

Each range is declared once, as roboshape/ranges.py data: here those of the sections every run reads and of the
pretrain section (the pretraining loop's, read by every encoder with a pretrain stage); with its registration those
of an encoder's own sections (roboshape/encoders: Kind.sections, checked by Kind.check), which are checked for that
encoder alone, so a value only another encoder needs (e.g. SAVi's decoder for env.resolution=32) never refuses an
R3M run. Checks that depend on the machine or on files (the device count, checkpoints, datasets) stay in the
stages. Importing this module is cheap; an encoder's check imports its model modules (JAX, Flax) only for that
encoder, and never starts a JAX backend. Defaults are configs/common.py's alone: every field checked here is
required.
"""
import os
from typing import Tuple

from roboshape import encoders
from roboshape import envs
from roboshape import ranges
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.errors import UserError
from roboshape.sim import spec as spec_lib

Int, Number, Ints, Flag = ranges.Int, ranges.Number, ranges.Ints, ranges.Flag

# The ranges of the sections every run reads, and of the pretrain section.
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
    "policy": (
        Int("policy.history", 1, "frames the policy sees"),
        Int("policy.width", 1, "the transformer's width"),
        Int("policy.num_layers", 1, "transformer blocks"),
        Int("policy.num_heads", 1, "attention heads, a divisor of policy.width"),
        Int("policy.mlp_ratio", 1, "the MLP's width over policy.width"),
        Int("policy.action_dim", 1, "action dimensions, 7 for the RoboShape envs"),
        Int("policy.num_modes", 1, "GMM modes"),
        Int("policy.train.steps", 1, "gradient steps; evaluate needs the checkpoint they leave"),
        Int("policy.train.batch_size", 1, "windows per gradient step"),
        Int("policy.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
        Int("policy.train.log_every", 1, "steps between TensorBoard logs"),
        Int("policy.train.eval_every", 1, "steps between validations"),
        Int("policy.train.checkpoint_every", 1, "steps between checkpoints"),
        Int("policy.train.val_batch_size", 1, "windows per validation batch"),
        Int("policy.train.max_val_samples", 1, "action targets scored per validation"),
        Int("policy.eval.history", 0, "frames seen at control time; 0: policy.history"),
        Number("policy.dropout", 0.0, "a dropout probability", high=1.0),
        Number("policy.min_scale", 0.0, "the floor on the GMM's scales"),
        Number("policy.train.learning_rate", 0.0, "the peak learning rate", low_ok=False),
        Number("policy.train.weight_decay", 0.0, "AdamW's weight decay"),
        Number("policy.train.grad_clip", 0.0, "the global gradient-norm clip", low_ok=False),
        Number("policy.eval.noise", 0.0, "the sampling noise, a fraction of the mode's scale"),
        Flag("policy.proprio", "a proprioception token per frame"),
        Flag("policy.hand_relative", "each token's object relative to the hand (needs policy.proprio)"),
        Flag("policy.frame_pool", "each frame's tokens pooled into one before the temporal transformer"),
        Ints("policy.train_seeds", 0, "one policy per training seed; (): one policy trained with config.seed",
             empty_ok=True, distinct=True),
    ),
    "eval": (
        Int("eval.num_seeds", 1, "evaluation seeds per level"),
        Int("eval.rollouts_per_seed", 1, "rollouts per evaluation seed"),
        Int("eval.seed_offset", 0, "the first evaluation env seed"),
        Int("eval.max_retries", 0, "re-runs of a rollout whose simulator worker died"),
        Int("eval.videos_per_level", 0, "rollouts recorded as videos per level"),
        Int("eval.video_fps", 1, "frames per second of the videos"),
    ),
    "pretrain": (
        Int("pretrain.train.steps", 0, "pretraining steps"),
        Int("pretrain.train.batch_size", 1, "clips per step"),
        Int("pretrain.train.clip_length", 1, "frames per clip"),
        Int("pretrain.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
        Int("pretrain.train.checkpoint_every", 1, "steps between checkpoints"),
        Int("pretrain.train.keep_checkpoints", 1, "checkpoints kept"),
        Int("pretrain.train.log_every", 1, "steps between TensorBoard logs"),
        Number("pretrain.train.learning_rate", 0.0, "the peak learning rate", low_ok=False),
        Number("pretrain.train.clip_norm", 0.0, "the global gradient-norm clip", low_ok=False),
        Number("pretrain.train.depth_weight", 0.0, "the weight of the depth MSE; 0: no depth target"),
        Int("pretrain.eval.every", 1, "steps between validations"),
        Int("pretrain.eval.episodes", 0, "validation episodes; 0: no validation"),
        Int("pretrain.eval.frames", 1, "frames of each validation episode"),
        Ints("pretrain.train_seeds", 0, "one pretraining run per seed, the best by validation kept; (): one run "
             "with config.seed", empty_ok=True, distinct=True),
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


def _check_policy(config) -> None:
  """The policy's ranges, heads dividing the width, the control-time history and action, the cache dtype."""
  # pylint: disable=import-outside-toplevel
  import numpy as np
  from roboshape.models import policy as policy_lib
  ranges.check(config, _RANGES["policy"])
  policy = config.policy
  if policy.width % policy.num_heads:
    raise UserError(f"policy.num_heads={policy.num_heads} does not divide policy.width={policy.width}: use a "
                    "divisor of the width.")
  if policy.eval.history > policy.history:
    raise UserError(f"policy.eval.history={policy.eval.history} exceeds policy.history={policy.history}: use at "
                    "most the training history (0: the training history).")
  ranges.Choice("policy.eval.action", policy_lib.ACTIONS, "the mixture mean, or a sampled mode").check(config)
  dtype = ranges.value(config, "policy.cache_dtype")
  try:
    floating = np.dtype(dtype).kind == "f"
  except TypeError:
    floating = False
  if not floating:
    raise UserError(f"policy.cache_dtype={dtype!r}: use a float dtype, float32 or float16 (halves the cache).")


def _check_eval(config) -> None:
  """The evaluation plan: known levels, seed counts, and env seeds that stay in the simulator's range."""
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  levels = ranges.value(config, "eval.levels")
  if (isinstance(levels, str) or not isinstance(levels, (tuple, list)) or not levels
      or any(l not in envs.LEVEL_NAMES for l in levels)):
    raise UserError(f"eval.levels={levels!r}: use a non-empty tuple of the levels "
                    f"{ranges.choices(envs.LEVEL_NAMES)}, e.g. \"('train', 'L1')\".")
  ranges.check(config, _RANGES["eval"])
  ev = config.eval
  if ev.rollouts_per_seed > closed_loop.SEED_STRIDE:
    raise UserError(f"eval.rollouts_per_seed={ev.rollouts_per_seed}: use at most {closed_loop.SEED_STRIDE} "
                    "(rollouts of one seed must not reach the next seed's env seeds).")
  last = ev.seed_offset + (ev.num_seeds - 1) * closed_loop.SEED_STRIDE + ev.rollouts_per_seed - 1
  if last > spec_lib.MAX_SEED:
    raise UserError(f"eval.seed_offset={ev.seed_offset} with eval.num_seeds={ev.num_seeds} reaches env seed {last}"
                    f", past the largest, {spec_lib.MAX_SEED}: lower eval.seed_offset or eval.num_seeds.")


def _check_pretrain(config) -> None:
  """The pretrain section: its ranges, what its clip is stated for, seeds that can be ranked, and depth in the data
  for a depth target."""
  from roboshape.train import pretrain  # pylint: disable=import-outside-toplevel
  ranges.check(config, _RANGES["pretrain"])
  ranges.Choice("pretrain.train.clip_norm_of", pretrain.CLIP_NORM_OF,
                "the loss whose gradient clip_norm bounds: the mean over a clip's values, or their sum (SAVi's)"
                ).check(config)
  p = config.pretrain
  if len(p.train_seeds) > 1 and p.eval.episodes < 1:
    raise UserError(f"pretrain.train_seeds={tuple(p.train_seeds)!r} selects a seed by validation, which "
                    f"pretrain.eval.episodes={p.eval.episodes} turns off: set pretrain.eval.episodes >= 1, or train "
                    "one seed.")
  weight = float(p.train.depth_weight)
  if weight > 0 and not config.env.depth and {"collect", "pretrain"} & set(config.stages):
    raise UserError(f"pretrain.train.depth_weight={weight} needs depth in the dataset: set "
                    "--config.env.depth=True, or --config.pretrain.train.depth_weight=0.")


# Sections shared by the encoders that list them in Kind.sections, checked here; an encoder's own are its Kind.check's.
_SHARED_SECTIONS = {"pretrain": _check_pretrain}


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


def check_single(config) -> None:
  """Raises UserError for the first field of a one-run config (no `grid`) that its stages cannot run with: the
  sections every run reads, then those of its encoder (Kind.sections: the shared ones here, then Kind.check)."""
  kind = _check_run(config)
  _check_env(config)
  ranges.check(config, _RANGES["data"] + _RANGES["sim"])
  _check_policy(config)
  _check_eval(config)
  for section in kind.sections:
    if section in _SHARED_SECTIONS:
      _SHARED_SECTIONS[section](config)
  if kind.check is not None:
    kind.check(config)
  _check_hand_relative(config, kind)


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


def check(config) -> None:
  """Raises UserError, one line naming the field and what to do, for the first problem of `config`.

  A grid config (a `grid` field, configs/reproduce.py) is checked as its grid fields, then as each of its runs
  (roboshape.grid.grid_configs).
  """
  if "grid" not in config:
    check_single(config)
    return
  from roboshape import grid  # pylint: disable=import-outside-toplevel
  _check_grid(config)
  _check_stages(config)
  for _, column, sub, _ in grid.grid_configs(config, ""):
    check_single(sub)
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
