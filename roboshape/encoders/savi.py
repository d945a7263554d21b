"""SAVi, the object-centric video encoder: pretrained in the run's workdir (roboshape/train/pretrain.py), served here
frozen from its checkpoint's params (no optimizer state is read).

  model, params, step = load(workdir)      # the SAVi module (roboshape/models/savi.py) and its newest params
  enc = load_encoder(workdir)              # a FrozenEncoder over K slots [B, K, D] per frame

With savi.train.seeds = (s1, s2, ...) the SAVi served is the seed the pretrain stage selected
(<workdir>/savi/selected.json, roboshape/train/pretrain.py), from <workdir>/savi/seed_<s>/checkpoints; the encoder's
identity names that folder, so a new selection changes it and the feature caches and policies made with another
seed are refused. With seeds = () it is <workdir>/savi/checkpoints, as before seeds existed.
"""
import functools
import os

from roboshape import encoders
from roboshape import rundir
from roboshape.errors import UserError


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
  """The folder of the model a pretrain stage serves from `stage_dir` (savi_dir, ae_dir): stage_dir itself for
  savi.train.seeds = () (or a config.json written before the field), else the folder of the seed its
  selected.json names; a UserError saying to run the pretrain stage when there is no selection of these seeds."""
  seeds = tuple(int(s) for s in config.savi.train.get("seeds", ()))
  if not seeds:
    return stage_dir
  selection = rundir.load_selection(stage_dir)
  command = launch_command(config, workdir)
  path = rundir.selection_path(stage_dir)
  if selection is None:
    raise UserError(f"no {title} seed is selected yet ({path} is missing): run the pretrain stage to train "
                    f"savi.train.seeds={seeds} to the end ({command}).")
  chosen_among = sorted(int(s["seed"]) for s in selection["seeds"])
  if chosen_among != sorted(seeds):
    raise UserError(f"{path} selected among seeds {tuple(chosen_among)}, the config trains savi.train.seeds="
                    f"{seeds}: run the pretrain stage again ({command}).")
  return rundir.seed_dir(stage_dir, int(selection["selected_seed"]))


def launch_command(config, workdir: str) -> str:
  """The command that runs `config`'s experiment on `workdir`, with its variant (the run identity check refuses
  another variant's run on that workdir)."""
  return f"python launch.py --config=configs/{config.name}.py:{config.variant} --workdir={workdir}"


def restore(config, workdir: str, model, stage_dir: str, title: str):
  """(params, step, checkpoint directory) of the newest checkpoint of `model` in <trained_dir>/checkpoints that
  restores (`trained_dir`: the selected seed's folder with savi.train.seeds); a UserError saying how to make one
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
  config = config or rundir.load_config(workdir)
  model = savi.build_model(config.savi, int(config.env.resolution))
  params, step, _ = restore(config, workdir, model, rundir.savi_dir(workdir), "SAVi")
  return model, params, step


def load_encoder(workdir: str, config=None):
  """The SAVi encoder trained in `workdir`, frozen: tokens are a frame's K slots [B, K, D].

  The state is the predicted slots for the next frame [B, K, D]; `init_state(B)` gives the learned first-frame
  slots drawn with a fixed key (savi.initial_slots), so encoding is deterministic and the same for every episode.
  """
  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp
  from roboshape.models import savi
  from roboshape.models.encoder import FrozenEncoder
  config = config or rundir.load_config(workdir)
  model = savi.build_model(config.savi, int(config.env.resolution))
  params, step, directory = restore(config, workdir, model, rundir.savi_dir(workdir), "SAVi")
  init = savi.initial_slots(model, params, 1)[0]
  return FrozenEncoder(
      name="savi", params=params, step=functools.partial(savi.frozen_step, model),
      init_state=lambda batch_size: jnp.broadcast_to(init, (batch_size, *init.shape)),
      num_tokens=model.num_slots, token_dim=model.slot_size, identity=f"savi:{os.path.abspath(directory)}@{step}")


def _build(config, workdir: str):
  del config          # the workdir's own config.json: the one its checkpoints were trained with
  return load_encoder(workdir)


encoders.register(encoders.Kind(
    name="savi", inputs=("image",), pretrain="roboshape.train.pretrain", build=_build, title="SAVi",
    description="slot attention for video, pretrained on the task's frames (K slots per frame)",
    evaluator="roboshape.eval.slots"))
