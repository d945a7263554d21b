"""One check of a whole experiment config before any stage runs: bad values fail in seconds, not hours later.

  config_check.check(config)     # raises roboshape.errors.UserError naming the first bad field and what to do

Every stage used to check its own fields when it started, so a bad `eval.levels` failed after collect, pretrain,
cache and train_policy had run. `check` covers the fields of every stage up front: types and ranges (counts are
ints >= 1, or >= 0 where 0 means something), learning rates > 0, probabilities in [0, 1], choices among known
values (task, encoder, stages, levels, ...), and the constraints between fields (policy.eval.history <=
policy.history, env.min_distractors <= env.max_distractors, savi.train.depth_weight > 0 needs env.depth, SAVi's
decoder size vs the frames it models, ...). It reports the FIRST problem found, in one line, as
"<field>=<value>: use ...". A grid config (configs/reproduce.py) is checked as each of its runs.

Sections only one encoder reads (savi, ae, baselines.*) are checked for that encoder alone, so a value another
encoder needs (e.g. SAVi's decoder for env.resolution=32) never refuses an R3M run. Checks that depend on the
machine or on files (the device count, checkpoints, datasets) stay in the stages. Importing this module is cheap;
the SAVi and baseline checks import their model modules (JAX, Flax) only for those encoders, and never start a
JAX backend. Defaults are configs/common.py's alone: every field checked here is required.
"""
import math
import os
import numbers
from typing import Any, Iterable, Sequence, Tuple

from roboshape import encoders
from roboshape import envs
from roboshape import rundir
from roboshape.errors import UserError
from roboshape.sim import spec as spec_lib

# Sections read only by some encoders: checked when config.encoder is one of them.
_ENCODER_SECTIONS = {
    "savi": ("savi",),
    "ae": ("savi", "ae"),             # the AE is trained with SAVi's settings (roboshape/train/pretrain_ae.py)
    "r3m": ("baselines.r3m",),
    "dino": ("baselines.dino",),
}
_POLICY_ACTIONS = ("mean", "sample")          # roboshape.models.policy.ControlSpec.action
_R3M_MIN_SIDE, _DINO_MIN_SIDE = 32, 16        # roboshape/baselines/r3m.py, dino.py: the smallest input side

# (field, minimum, what it is): ints >= minimum.
_INTS = {
    "run": (
        ("seed", 0, "the seed of initialisation, data order and sampling"),
    ),
    "data": (
        ("data.train_episodes", 1, "successful expert demos to collect for training"),
        ("data.min_val_episodes", 1, "the fewest validation demos; pretrain and train_policy validate on them"),
    ),
    "sim": (
        ("sim.num_workers", 0, "simulator worker processes; 0: one per CPU core"),
    ),
    "policy": (
        ("policy.history", 1, "frames the policy sees"),
        ("policy.width", 1, "the transformer's width"),
        ("policy.num_layers", 1, "transformer blocks"),
        ("policy.num_heads", 1, "attention heads, a divisor of policy.width"),
        ("policy.mlp_ratio", 1, "the MLP's width over policy.width"),
        ("policy.action_dim", 1, "action dimensions, 7 for the RoboShape envs"),
        ("policy.num_modes", 1, "GMM modes"),
        ("policy.chunk", 1, "actions predicted per step; 1: no chunking"),
        ("policy.train.steps", 1, "gradient steps; evaluate needs the checkpoint they leave"),
        ("policy.train.batch_size", 1, "windows per gradient step"),
        ("policy.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
        ("policy.train.log_every", 1, "steps between TensorBoard logs"),
        ("policy.train.eval_every", 1, "steps between validations"),
        ("policy.train.checkpoint_every", 1, "steps between checkpoints"),
        ("policy.train.val_batch_size", 1, "windows per validation batch"),
        ("policy.train.max_val_samples", 1, "action targets scored per validation"),
        ("policy.eval.history", 0, "frames seen at control time; 0: policy.history"),
    ),
    "eval": (
        ("eval.num_seeds", 1, "evaluation seeds per level"),
        ("eval.rollouts_per_seed", 1, "rollouts per evaluation seed"),
        ("eval.seed_offset", 0, "the first evaluation env seed"),
        ("eval.max_retries", 0, "re-runs of a rollout whose simulator worker died"),
        ("eval.videos_per_level", 0, "rollouts recorded as videos per level"),
        ("eval.video_fps", 1, "frames per second of the videos"),
    ),
    "savi": (
        ("savi.num_slots", 1, "slots per frame"),
        ("savi.slot_size", 1, "the width of a slot, a multiple of savi.predictor.num_heads"),
        ("savi.pool", 1, "the factor frames are average-pooled by, a divisor of env.resolution"),
        ("savi.num_iterations", 1, "slot-attention iterations per frame"),
        ("savi.slot_mlp_size", 0, "the slot MLP's width; 0: no MLP"),
        ("savi.encoder.kernel_size", 1, "the CNN's kernel side"),
        ("savi.encoder.mlp_size", 1, "the encoder MLP's width"),
        ("savi.encoder.output_size", 1, "the encoder's feature width"),
        ("savi.predictor.num_heads", 1, "the predictor's attention heads"),
        ("savi.predictor.mlp_size", 1, "the predictor MLP's width"),
        ("savi.decoder.grid_size", 0, "the broadcast grid's side; 0: automatic"),
        ("savi.decoder.kernel_size", 1, "the decoder's kernel side"),
        ("savi.train.steps", 0, "pretraining steps"),
        ("savi.train.batch_size", 1, "clips per step"),
        ("savi.train.clip_length", 1, "frames per clip"),
        ("savi.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
        ("savi.train.checkpoint_every", 1, "steps between checkpoints"),
        ("savi.train.keep_checkpoints", 1, "checkpoints kept"),
        ("savi.train.log_every", 1, "steps between TensorBoard logs"),
        ("savi.eval.every", 1, "steps between validations"),
        ("savi.eval.episodes", 0, "validation episodes; 0: no validation"),
        ("savi.eval.frames", 1, "frames of each validation episode"),
        ("savi.eval.figure_frames", 0, "frames in each validation figure"),
    ),
    "ae": (
        ("ae.latent_size", 0, "the AE's token width; 0: savi.slot_size"),
    ),
    "baselines.r3m": (
        ("baselines.r3m.input_size", 0, "the side frames are resized to; 0: their own"),
    ),
    "baselines.dino": (
        ("baselines.dino.input_size", 0, "the side frames are resized to; 0: their own"),
    ),
}

# (field, minimum, minimum allowed?, maximum or None, what it is): finite numbers in range.
_NUMBERS = {
    "data": (
        ("data.val_fraction", 0.0, True, 1.0, "validation demos per training demo"),
    ),
    "sim": (
        ("sim.step_timeout", 0.0, False, None, "seconds a worker may take for one reset or step"),
        ("sim.episode_timeout", 0.0, False, None, "seconds a worker may take for one expert episode"),
    ),
    "policy": (
        ("policy.dropout", 0.0, True, 1.0, "a dropout probability"),
        ("policy.min_scale", 0.0, True, None, "the floor on the GMM's scales"),
        ("policy.train.learning_rate", 0.0, False, None, "the peak learning rate"),
        ("policy.train.weight_decay", 0.0, True, None, "AdamW's weight decay"),
        ("policy.train.grad_clip", 0.0, False, None, "the global gradient-norm clip"),
        ("policy.eval.noise", 0.0, True, None, "the sampling noise, a fraction of the mode's scale"),
        ("policy.eval.ensemble_decay", 0.0, True, None, "k in the ensembling weights exp(-k i)"),
    ),
    "savi": (
        ("savi.train.learning_rate", 0.0, False, None, "the peak learning rate"),
        ("savi.train.clip_norm", 0.0, False, None, "the global gradient-norm clip"),
        ("savi.train.depth_weight", 0.0, True, None, "the weight of the depth MSE; 0: no depth target"),
    ),
}


# ----------------------------------------------------------------------------------------------------------------
# Reading fields and the generic checks.


def _value(config, path: str) -> Any:
  """config's field at dotted `path`; a UserError when it is absent."""
  node = config
  for key in path.split("."):
    if not hasattr(node, "keys") or key not in node:
      raise UserError(f"the config has no field {path}; build configs with configs/common.py "
                      "(e.g. configs/pick_savi.py) and override fields with --config.<field>=<value>.")
    node = node[key]
  return node


def _is_int(value: Any) -> bool:
  return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
  return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _choices(values: Iterable[Any]) -> str:
  return ", ".join(str(v) for v in values)


def check_int(config, path: str, low: int, what: str) -> int:
  """The int at `path`; a UserError unless it is an int >= low."""
  value = _value(config, path)
  if not _is_int(value) or value < low:
    raise UserError(f"{path}={value!r}: use an int >= {low} ({what}).")
  return int(value)


def check_number(config, path: str, low: float, low_ok: bool, high, what: str) -> float:
  """The number at `path`; a UserError unless it is finite, > low (>= low if low_ok) and <= high (if any)."""
  value = _value(config, path)
  above = _is_number(value) and (value >= low if low_ok else value > low)
  if not above or (high is not None and value > high):
    if high is not None:
      wanted = f"a number in [{low:g}, {high:g}]"
    else:
      wanted = f"a number {'>=' if low_ok else '>'} {low:g}"
    raise UserError(f"{path}={value!r}: use {wanted} ({what}).")
  return float(value)


def check_choice(config, path: str, choices: Sequence[Any], what: str) -> Any:
  """The value at `path`; a UserError unless it is one of `choices`."""
  value = _value(config, path)
  if value not in tuple(choices):
    raise UserError(f"{path}={value!r}: use one of {_choices(choices)} ({what}).")
  return value


def check_ints(config, path: str, low: int, what: str, length: int = 0) -> Tuple[int, ...]:
  """The tuple at `path`; a UserError unless it is a non-empty tuple of ints >= low (of `length` ints if > 0)."""
  value = _value(config, path)
  ok = isinstance(value, (tuple, list)) and value and all(_is_int(v) and v >= low for v in value)
  if not ok:
    raise UserError(f"{path}={value!r}: use a non-empty tuple of ints >= {low} ({what}).")
  if length and len(value) != length:
    raise UserError(f"{path}={tuple(value)!r} has {len(value)} entries: use {length} ({what}).")
  return tuple(int(v) for v in value)


def _check_tables(config, section: str) -> None:
  for path, low, what in _INTS.get(section, ()):
    check_int(config, path, low, what)
  for path, low, low_ok, high, what in _NUMBERS.get(section, ()):
    check_number(config, path, low, low_ok, high, what)


# ----------------------------------------------------------------------------------------------------------------
# The sections.


def _check_stages(config) -> Tuple[str, ...]:
  """config.stages: a tuple of known stage names (rundir.STAGES)."""
  names = _value(config, "stages")
  if isinstance(names, str) or not isinstance(names, (tuple, list)):
    raise UserError(f"stages={names!r}: use a tuple of stages, e.g. \"('collect', 'pretrain')\", of "
                    f"{_choices(rundir.STAGES)}.")
  unknown = [s for s in names if s not in rundir.STAGES]
  if unknown:
    raise UserError(f"unknown stage(s) {_choices(unknown)} in stages; use some of "
                    f"{_choices(rundir.STAGES)}.")
  return tuple(names)


def _check_run(config) -> None:
  """task, encoder, stages and seed: known names, a pretrain stage only for an encoder that has one."""
  check_choice(config, "task", envs.TASKS, "the task")
  kind = encoders.get(check_choice(config, "encoder", encoders.names(),
                                   "a registered encoder; add one as a module in roboshape/encoders/"))
  if "pretrain" in _check_stages(config) and not kind.pretrain:
    raise UserError(f"the {kind.name} encoder has no pretrain stage; drop it from --config.stages.")
  _check_tables(config, "run")


def _check_env(config) -> None:
  """The env section, by the simulator bridge's own EnvSpec (distractors, horizon, backend)."""
  resolution = _value(config, "env.resolution")
  if not _is_int(resolution) or not envs.MIN_RESOLUTION <= resolution <= envs.MAX_RESOLUTION:
    raise UserError(f"env.resolution={resolution!r}: use an int in [{envs.MIN_RESOLUTION}, {envs.MAX_RESOLUTION}] "
                    "(the camera's side in pixels; 64 by default).")
  spec_lib.EnvSpec.from_config(config)
  if not isinstance(_value(config, "env.depth"), bool):
    raise UserError(f"env.depth={config.env.depth!r}: use True or False (also store the camera's depth).")


def _check_policy(config) -> None:
  """The policy's ranges, heads dividing the width, the control-time history and action, proprio a bool, the cache
  dtype."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  _check_tables(config, "policy")
  policy = config.policy
  if policy.width % policy.num_heads:
    raise UserError(f"policy.num_heads={policy.num_heads} does not divide policy.width={policy.width}: use a "
                    "divisor of the width.")
  if policy.eval.history > policy.history:
    raise UserError(f"policy.eval.history={policy.eval.history} exceeds policy.history={policy.history}: use at "
                    "most the training history (0: the training history).")
  check_choice(config, "policy.eval.action", _POLICY_ACTIONS, "the mixture mean, or a sampled mode")
  if not isinstance(_value(config, "policy.proprio"), bool):
    raise UserError(f"policy.proprio={policy.proprio!r}: use True or False (a proprioception token per frame).")
  seeds = _value(config, "policy.train_seeds")
  if (isinstance(seeds, str) or not isinstance(seeds, (tuple, list)) or len(set(seeds)) != len(seeds)
      or not all(_is_int(s) and s >= 0 for s in seeds)):
    raise UserError(f"policy.train_seeds={seeds!r}: use a tuple of distinct ints >= 0 (one policy per training "
                    "seed), or () for one policy trained with config.seed.")
  dtype = _value(config, "policy.cache_dtype")
  try:
    floating = np.dtype(dtype).kind == "f"
  except TypeError:
    floating = False
  if not floating:
    raise UserError(f"policy.cache_dtype={dtype!r}: use a float dtype, float32 or float16 (halves the cache).")


def _check_eval(config) -> None:
  """The evaluation plan: known levels, seed counts, and env seeds that stay in the simulator's range."""
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  levels = _value(config, "eval.levels")
  if (isinstance(levels, str) or not isinstance(levels, (tuple, list)) or not levels
      or any(l not in envs.LEVEL_NAMES for l in levels)):
    raise UserError(f"eval.levels={levels!r}: use a non-empty tuple of the levels "
                    f"{_choices(envs.LEVEL_NAMES)}, e.g. \"('train', 'L1')\".")
  _check_tables(config, "eval")
  ev = config.eval
  if ev.rollouts_per_seed > closed_loop.SEED_STRIDE:
    raise UserError(f"eval.rollouts_per_seed={ev.rollouts_per_seed}: use at most {closed_loop.SEED_STRIDE} "
                    "(rollouts of one seed must not reach the next seed's env seeds).")
  last = ev.seed_offset + (ev.num_seeds - 1) * closed_loop.SEED_STRIDE + ev.rollouts_per_seed - 1
  if last > spec_lib.MAX_SEED:
    raise UserError(f"eval.seed_offset={ev.seed_offset} with eval.num_seeds={ev.num_seeds} reaches env seed {last}"
                    f", past the largest, {spec_lib.MAX_SEED}: lower eval.seed_offset or eval.num_seeds.")


def _check_savi(config) -> None:
  """SAVi's section (also the AE's training settings): ranges, layer tuples, then the model's own check of modes
  and fit to the frames (roboshape.models.savi.check_config, which the pretrain stage runs too, with the device
  count: that starts a JAX backend, which must not hold an accelerator before the collect stage)."""
  from roboshape.models import savi  # pylint: disable=import-outside-toplevel
  _check_tables(config, "savi")
  c = config.savi
  for part in ("encoder", "decoder"):
    features = check_ints(config, f"savi.{part}.features", 1, f"channels of each {part} layer")
    check_ints(config, f"savi.{part}.strides", 1, f"one stride per savi.{part}.features layer", len(features))
  savi.check_config(c, config.env.resolution)
  if c.slot_size % c.predictor.num_heads:
    raise UserError(f"savi.predictor.num_heads={c.predictor.num_heads} does not divide savi.slot_size="
                    f"{c.slot_size}: use a divisor of the slot size.")
  if not isinstance(c.eval.background_ids, (tuple, list)) or not all(
      _is_int(i) and i >= 0 for i in c.eval.background_ids):
    raise UserError(f"savi.eval.background_ids={c.eval.background_ids!r}: use a tuple of segmentation ids >= 0.")
  seeds = _value(config, "savi.train.seeds")
  if isinstance(seeds, str) or not isinstance(seeds, (tuple, list)) or not all(
      _is_int(s) and s >= 0 for s in seeds) or len(set(seeds)) != len(seeds):
    raise UserError(f"savi.train.seeds={seeds!r}: use a tuple of distinct ints >= 0, e.g. \"(0, 1, 2)\" (one "
                    "pretraining run per seed, the best by validation kept), or () for one run with config.seed.")
  if len(seeds) > 1 and c.eval.episodes < 1:
    raise UserError(f"savi.train.seeds={tuple(seeds)!r} selects a seed by validation, which "
                    f"savi.eval.episodes={c.eval.episodes} turns off: set savi.eval.episodes >= 1, or train one seed.")
  depth_weight = savi.depth_weight(c)
  if depth_weight > 0 and not config.env.depth and {"collect", "pretrain"} & set(config.stages):
    raise UserError(f"savi.train.depth_weight={depth_weight} needs depth in the dataset: set "
                    "--config.env.depth=True, or --config.savi.train.depth_weight=0.")


def _check_baseline(config, name: str, archs: Sequence[str], min_side: int) -> None:
  """baselines.<name>: a known architecture and frames at least `min_side` pixels a side."""
  section = f"baselines.{name}"
  check_choice(config, f"{section}.arch", archs, f"the {name.upper()} network")
  _check_tables(config, section)
  input_size = int(_value(config, f"{section}.input_size"))
  side = input_size or config.env.resolution
  if side < min_side:
    raise UserError(f"{section}.input_size={input_size} gives {side}x{side} inputs; {name.upper()} needs at least "
                    f"{min_side}: set it to 0 with env.resolution >= {min_side}, or to 224.")


def _check_r3m(config) -> None:
  from roboshape.baselines import resnet  # pylint: disable=import-outside-toplevel
  _check_baseline(config, "r3m", tuple(resnet.ARCHS), _R3M_MIN_SIDE)


def _check_dino(config) -> None:
  from roboshape.baselines import vit  # pylint: disable=import-outside-toplevel
  _check_baseline(config, "dino", tuple(vit.ARCHS), _DINO_MIN_SIDE)


_SECTION_CHECKS = {
    "savi": _check_savi,
    "ae": lambda config: _check_tables(config, "ae"),
    "baselines.r3m": _check_r3m,
    "baselines.dino": _check_dino,
}


def _check_grid(config) -> None:
  """grid.tasks and grid.encoders: non-empty tuples of known tasks and registered encoders; grid.publish a folder."""
  for field, known in (("grid.tasks", envs.TASKS), ("grid.encoders", encoders.names())):
    value = _value(config, field)
    if isinstance(value, str) or not isinstance(value, (tuple, list)) or not value or any(
        v not in known for v in value):
      raise UserError(f"{field}={value!r}: use a non-empty tuple of {_choices(known)}.")
  unknown = [t for t in config.grid.get("train_seeds", {}) if t not in envs.TASKS]
  if unknown:
    raise UserError(f"grid.train_seeds names {', '.join(map(repr, unknown))}: use tasks among {_choices(envs.TASKS)}.")
  publish = config.grid.get("publish", "")
  if not isinstance(publish, str):
    raise UserError(f"grid.publish={publish!r}: use a folder (e.g. \"results/small\") or \"\" to publish nothing.")
  if publish and os.path.exists(publish) and not os.path.isdir(publish):
    raise UserError(f"grid.publish={publish!r} is a file; give a folder for the finished runs' results.")
  if "lanes" in config.grid:
    check_int(config, "grid.lanes", 1, "runs at once, each pinned to its share of the CPU cores (roboshape/lanes.py)")


def check_single(config) -> None:
  """Raises UserError for the first field of a one-run config (no `grid`) that its stages cannot run with."""
  _check_run(config)
  _check_env(config)
  for section in ("data", "sim"):
    _check_tables(config, section)
  _check_policy(config)
  _check_eval(config)
  for section in _ENCODER_SECTIONS.get(config.encoder, ()):
    _SECTION_CHECKS[section](config)


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
  for _, _, sub, _ in grid.grid_configs(config, ""):
    check_single(sub)
