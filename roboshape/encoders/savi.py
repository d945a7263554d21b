"""SAVi, the object-centric video encoder: pretrained in the run's workdir (roboshape/train/pretrain.py), served here
frozen from its checkpoint's params (no optimizer state is read).

  model, params, step = load(workdir)      # the SAVi module (roboshape/models/savi.py) and its newest params
  enc = load_encoder(workdir)              # a FrozenEncoder over K slots [B, K, D] per frame

With pretrain.train_seeds = (s1, s2, ...) the SAVi served is the seed the pretrain stage selected
(<workdir>/savi/selected.json, roboshape/train/pretrain.py), from <workdir>/savi/seed_<s>/checkpoints; the encoder's
identity names that folder, so a new selection changes it and the feature caches and policies made with another
seed are refused. With seeds = () it is <workdir>/savi/checkpoints. A run with pretrain.from_workdir set serves the
SAVi of the run that workdir holds (`pretrained_source`), as the AE does (roboshape/encoders/ae.py).

The ranges of the savi section are declared here (RANGES, and `frame_ranges` for the frame encoder and decoder the
AE shares) and checked by `check`, with SAVi's modes and its fit to the frames (roboshape/models/savi.py).
"""
import functools
import json
import os

from roboshape.encoders import registry
from roboshape import ranges
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.errors import UserError


def frame_ranges(name: str) -> tuple:
  """The ranges of a frame model's pool, CNN encoder and spatial-broadcast decoder in config section `name` (savi,
  ae)."""
  out = [ranges.Int(f"{name}.pool", 1, "the factor frames are average-pooled by, a divisor of env.resolution")]
  for part, what in (("encoder", "the CNN's"), ("decoder", "the decoder's")):
    out.append(ranges.Ints(f"{name}.{part}.features", 1, f"channels of each {part} layer"))
    out.append(ranges.Ints(f"{name}.{part}.strides", 1, f"one stride per {name}.{part}.features layer",
                           length_of=f"{name}.{part}.features"))
    out.append(ranges.Int(f"{name}.{part}.kernel_size", 1, f"{what} kernel side"))
  out += [ranges.Int(f"{name}.encoder.mlp_size", 1, "the encoder MLP's width"),
          ranges.Int(f"{name}.encoder.output_size", 1, "the encoder's feature width"),
          ranges.Int(f"{name}.decoder.grid_size", 0, "the broadcast grid's side; 0: automatic")]
  return tuple(out)


RANGES = (
    ranges.Int("savi.num_slots", 1, "slots per frame"),
    ranges.Int("savi.slot_size", 1, "the width of a slot, a multiple of savi.predictor.num_heads"),
    ranges.Int("savi.num_iterations", 1, "slot-attention iterations per frame"),
    ranges.Int("savi.slot_mlp_size", 0, "the slot MLP's width; 0: no MLP"),
    ranges.Int("savi.full_grid", 0, "channels of the full-resolution path; 0: slot attention on the CNN's grid"),
    ranges.Int("savi.predictor.num_heads", 1, "the predictor's attention heads"),
    ranges.Int("savi.predictor.mlp_size", 1, "the predictor MLP's width"),
    ranges.Flag("savi.predictor.identity_init", "the predictor starts as LayerNorm"),
    ranges.Ints("savi.eval.background_ids", 0, "segmentation ids FG-ARI and mIoU ignore", empty_ok=True),
    ranges.Int("savi.eval.figure_frames", 0, "frames in each validation figure"),
) + frame_ranges("savi")


def check(config) -> None:
  """Raises UserError for the first bad field of the savi section: RANGES, then SAVi's modes and fit to the frames
  (roboshape.models.savi.check_config, which imports JAX but starts no backend), and heads that divide the slot."""
  from roboshape.models import savi  # pylint: disable=import-outside-toplevel
  ranges.check(config, RANGES)
  c = config.savi
  savi.check_config(c, int(config.env.resolution))
  if c.slot_size % c.predictor.num_heads:
    raise UserError(f"savi.predictor.num_heads={c.predictor.num_heads} does not divide savi.slot_size="
                    f"{c.slot_size}: use a divisor of the slot size.")
  shown = len(cue_ids(config))
  if c.init_mean == "cues" and c.num_slots < shown:
    raise UserError(f"savi.num_slots={c.num_slots} with savi.init_mean='cues': a conditional SAVi gives each object "
                    f"a scene can show its own slot, {shown} with env.max_distractors={config.env.max_distractors}: "
                    f"use at least {shown} slots.")


def cue_ids(config) -> tuple:
  """The segmentation ids a scene of `config` can show with the robot as one object (backdrop, table, robot, cube,
  goal, its distractors): a conditional SAVi's slot k starts on id k (roboshape/models/savi.py first_frame_cues)."""
  from roboshape.envs import ids  # pylint: disable=import-outside-toplevel
  return tuple(range(ids.FIRST_DISTRACTOR + int(config.env.max_distractors)))


def abstract_params(model, resolution: int):
  """The shapes and dtypes of a frame-reconstruction model's params (SAVi's, the AE's), on the default device, as
  a checkpoint restores them; nothing is computed."""
  # pylint: disable=import-outside-toplevel
  import jax
  import jax.numpy as jnp
  dummy = jnp.zeros((1, 1, resolution, resolution, 3), jnp.float32)
  like = jax.eval_shape(lambda: model.init({"params": jax.random.key(0), "slots": jax.random.key(1)}, dummy)["params"])
  device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device), like)


def trained_dir(config, workdir: str, stage_dir: str, title: str) -> str:
  """The folder of the model a pretrain stage serves from `stage_dir` (rundir.pretrain_dir): stage_dir itself for
  pretrain.train_seeds = (), else the folder of the seed its selected.json names; a UserError saying to run the
  pretrain stage when there is no selection of these seeds."""
  seeds = rundir.train_seeds(config, "pretrain")
  if seeds == (None,):
    return stage_dir
  selection = rundir.load_selection(stage_dir)
  command = launch_command(config, workdir)
  path = rundir.selection_path(stage_dir)
  if selection is None:
    raise UserError(f"no {title} seed is selected yet ({path} is missing): run the pretrain stage to train "
                    f"pretrain.train_seeds={seeds} to the end ({command}).")
  chosen_among = sorted(int(s["seed"]) for s in selection["seeds"])
  if chosen_among != sorted(seeds):
    raise UserError(f"{path} selected among seeds {tuple(chosen_among)}, the config trains pretrain.train_seeds="
                    f"{seeds}: run the pretrain stage again ({command}).")
  return rundir.seed_dir(stage_dir, int(selection["selected_seed"]))


def launch_command(config, workdir: str) -> str:
  """The command that runs `config`'s experiment on `workdir`, with its variant (the run identity check refuses
  another variant's run on that workdir) and its column's options (roboshape/encoders/columns.py)."""
  return (f"python launch.py --config=configs/{config.task}_{config.encoder}.py:{config.variant}"
          f"{columns.flags(columns.of_config(config))} --workdir={workdir}")


# What a pretrain stage reads, SAVi's and the AE's alike: two runs that agree on these pretrain the same model.
PRETRAINING_READS = ("encoder", "seed", "env", "data", "pretrain", "savi", "ae")


def pretrained_source(config, workdir: str):
  """(workdir, config) of the run whose pretrain stage trained this run's encoder: this run, or the run its
  pretrain.from_workdir names (rundir.pretrained_workdir) with that run's config.json. That config must agree with
  this one on PRETRAINING_READS (the dataset by its folder, pretrain.from_workdir aside), else a UserError: a
  policy is never trained on an encoder pretrained otherwise than its config says."""
  source = rundir.pretrained_workdir(config, workdir)
  if source == workdir:
    return workdir, config
  if not os.path.exists(rundir.config_path(source)):
    raise UserError(f"pretrain.from_workdir={source!r} holds no run yet ({rundir.config_path(source)} is missing): "
                    f"run that run's pretrain stage first (a grid runs it before this one), or set "
                    "pretrain.from_workdir=\"\" to pretrain in this run's workdir.")
  theirs = rundir.load_config(source)
  differ = [key for key in PRETRAINING_READS if _pretraining_view(config, workdir, key)
            != _pretraining_view(theirs, source, key)]
  if differ:
    raise UserError(f"pretrain.from_workdir={source!r} was pretrained with other settings ({', '.join(differ)} "
                    f"differ from this run's): set pretrain.from_workdir=\"\" to pretrain in this run's workdir, "
                    "or point it at a run pretrained as this config says.")
  return source, theirs


def _pretraining_view(config, workdir: str, key: str):
  """config[key] as JSON data, the dataset's folder resolved (rundir.data_root) and pretrain.from_workdir left out."""
  value = config.get(key)
  value = json.loads(json.dumps(value.to_dict() if hasattr(value, "to_dict") else value))
  if key == "data":
    value["dir"] = os.path.abspath(rundir.data_root(config, workdir))
  if key == "pretrain":
    value.pop("from_workdir", None)
  return value


def restore(config, workdir: str, model, stage_dir: str, title: str):
  """(params, step, checkpoint directory) of the newest checkpoint of `model` in <trained_dir>/checkpoints that
  restores (`trained_dir`: the selected seed's folder with pretrain.train_seeds); a UserError saying how to make one
  when there is none."""
  from roboshape import checkpoint  # pylint: disable=import-outside-toplevel
  directory = rundir.checkpoints(trained_dir(config, workdir, stage_dir, title))
  params, step = checkpoint.restore_params(
      directory, abstract_params(model, int(config.env.resolution)),
      f"no {title} checkpoint in {directory}; run the pretrain stage first "
      f"({launch_command(config, workdir)}).")
  return params, step, directory


def load(workdir: str, config=None):
  """(model, params, step) of the SAVi trained in `workdir` (its newest checkpoint that restores); `config`: the
  workdir's config.json when None."""
  from roboshape.models import savi  # pylint: disable=import-outside-toplevel
  workdir, config = pretrained_source(config or rundir.load_config(workdir), workdir)
  model = savi.model_from_config(config)
  params, step, _ = restore(config, workdir, model, rundir.pretrain_dir(workdir, "savi"), "SAVi")
  return model, params, step


def load_encoder(workdir: str, config=None, located: bool = False):
  """The SAVi encoder trained in `workdir`, frozen: tokens are a frame's K slots [B, K, D].

  The state is the predicted slots for the next frame [B, K, D]; `init_state(B)` gives the learned first-frame
  slots drawn with a fixed key (savi.initial_slots), so encoding is deterministic and the same for every episode.
  `located`: it also reads the camera's depth and appends each slot's location to its token ([B, K, D + 3]:
  models/savi.py located_step), and says where each slot's object is (FrozenEncoder.points, for
  policy.hand_relative). A conditional SAVi (savi.init_mean "cues") also reads the segmentation: its state is the
  predicted slots and whether the episode has begun, and an episode's first slots come from the cues of its first
  frame's segmentation, the simulator's privileged view of where each object is at the start (later frames' are
  not read).
  """
  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp
  from roboshape.models import savi
  from roboshape.models.encoder import FrozenEncoder
  workdir, config = pretrained_source(config or rundir.load_config(workdir), workdir)
  model = savi.model_from_config(config)
  params, step, directory = restore(config, workdir, model, rundir.pretrain_dir(workdir, "savi"), "SAVi")
  identity = f"savi:{os.path.abspath(directory)}@{step}"
  inputs = ("image",) + (("depth",) if located else ())
  if savi.conditional(model):
    shape = (model.num_slots, model.slot_size)
    init_state = lambda batch_size: (jnp.zeros((batch_size, *shape)), jnp.zeros((batch_size,), bool))
    inputs = ("image", "segmentation") + inputs[1:]
  else:
    init = savi.initial_slots(model, params, 1)[0]
    init_state = lambda batch_size: jnp.broadcast_to(init, (batch_size, *init.shape))
  common = dict(name="savi", params=params, num_tokens=model.num_slots, init_state=init_state, inputs=inputs)
  step = functools.partial(_step, model, located)
  if not located:
    return FrozenEncoder(step=step, token_dim=model.slot_size, identity=identity, **common)
  return FrozenEncoder(step=step, token_dim=model.slot_size + 3, identity=f"{identity}:located",
                       points=slot_points, **common)


def _step(model, located: bool, params, state, obs):
  """The frozen step of `load_encoder`: the frame's slots (located: with where each attends), the next state."""
  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp
  from roboshape.envs import ids
  from roboshape.models import savi
  image = obs if not isinstance(obs, dict) else obs["image"]
  if savi.conditional(model):
    slots, begun = state
    cues = savi.first_frame_cues(ids.robot_as_one(obs["segmentation"]), model.num_slots)
    first = savi.initial_slots(model, params, image.shape[0], cues)
    state = jnp.where(begun[:, None, None], slots, first)
  if located:
    tokens, predicted = savi.located_step(model, params, state, image, obs["depth"])
  else:
    tokens, predicted = savi.frozen_step(model, params, state, image)
  if savi.conditional(model):
    predicted = (predicted, jnp.ones_like(begun))
  return tokens, predicted


def slot_points(tokens):
  """tokens [..., K, D + 3] of a located SAVi -> (world points [..., K, 3], valid [..., K]): each slot's attended
  centre at its attended depth, through the front camera's calibration (roboshape/envs/camera.py), as the objects
  tokens' centroids are; valid where the slot attends somewhere with a depth."""
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  row, col, depth = tokens[..., -3], tokens[..., -2], tokens[..., -1]
  return camera.unproject(row, col, depth), depth > 0


def _build(config, workdir: str):
  """The SAVi of the workdir (its own config.json: the one its checkpoints were trained with), located when the
  run's `config` asks for policy.hand_relative."""
  located = bool(config is not None and config.policy.hand_relative)
  return load_encoder(workdir, located=located)


def _model(config):
  from roboshape.models import savi  # pylint: disable=import-outside-toplevel
  return savi.model_from_config(config)


registry.register(registry.Kind(
    name="savi", inputs=("image",), pretrain="loop", build=_build, title="SAVi",
    description="slot attention for video, pretrained on the task's frames (K slots per frame)",
    evaluator="slots",
    model=registry.PretrainModel(build=_model, selection=registry.Selection("fg_ari", True, "FG-ARI")),
    sections=("pretrain", "savi"), check=check, baseline=False, slot_videos=True, family="object-centric", order=3,
    views=True,
    tokens=lambda config: f"{config.savi.num_slots} x {config.savi.slot_size}",
    points=lambda config: "" if config.env.depth else (
        "its slots are placed in 3-D only with the camera's depth: set env.depth=True (and collect the dataset "
        "with it)")))
