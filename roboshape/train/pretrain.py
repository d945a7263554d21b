"""The "pretrain" stage: SAVi trained by video reconstruction on the task's demos, then served as a frozen encoder.

  python launch.py --config=configs/pick_savi.py:small --config.stages='("pretrain",)' --workdir=runs/pick_savi
  enc = roboshape.load_encoder("runs/pick_savi")      # -> load_encoder below, a FrozenEncoder over K slots of size D

Training: clips of `config.savi.train.clip_length` frames from the dataset's train split, MSE reconstruction, Adam
with linear warmup, cosine decay and global-norm clipping. The jitted train step shards the batch over the devices
of a 1-D mesh ("data") and keeps parameters replicated. Writes under <workdir>/savi/: checkpoints/ (orbax; resumed
after a kill at the same step, with the same data order since batch i of the dataset's deterministic order always
feeds step i), tb/ (TensorBoard scalars: loss, recon_mse, grad_norm, lr, and val FG-ARI / mIoU of the slot masks,
see roboshape/eval/decomposition.py), figures/ (input, reconstruction and every slot per eval, as PNG),
val_metrics.json and val_metrics.png (every validation result so far, across resumes, and its curve).
A non-finite loss stops training with the step and the batch's episode seeds; the last good checkpoint stays.

The training loop (`fit`), the compiled train step (`Compiled`), the data (`data_source`) and checkpoint restore
(`restore_latest`) take any reconstruction model of the frames, so other encoders pretrained on the same settings
reuse them (roboshape/train/pretrain_ae.py).
"""
import dataclasses
import functools
import itertools
import json
import math
import os
import time
from typing import Any, Callable, Dict, Iterator, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from roboshape.cli import UserError
from roboshape.envs import ids
from roboshape.eval import decomposition
from roboshape.models import savi
from roboshape.models.encoder import FrozenEncoder
from roboshape.train import history as history_lib
from roboshape.train.checkpoint import Checkpointer

INIT_SLOTS_SEED = 0  # the fixed key of the frozen encoder's first-frame slots


def savi_dir(workdir: str) -> str:
  return os.path.join(workdir, "savi")


def validate_config(config) -> None:
  """Raises UserError when the SAVi section cannot work with the env's resolution or the machine's devices."""
  c = config.savi
  if len(c.encoder.features) != len(c.encoder.strides):
    raise UserError(f"savi.encoder.features ({len(c.encoder.features)} layers) and savi.encoder.strides "
                    f"({len(c.encoder.strides)}) must have the same length.")
  if len(c.decoder.features) != len(c.decoder.strides):
    raise UserError(f"savi.decoder.features ({len(c.decoder.features)} layers) and savi.decoder.strides "
                    f"({len(c.decoder.strides)}) must have the same length.")
  for field, value, choices in (("init_mean", c.get("init_mean", "shared"), savi.INIT_MEANS),
                                ("slot_gradient", c.get("slot_gradient", "full"), savi.SLOT_GRADIENTS),
                                ("decoder.rgb", c.decoder.get("rgb", "spatial"), savi.DECODER_RGBS),
                                ("decoder.position", c.decoder.get("position", "coords"), savi.DECODER_POSITIONS)):
    if value not in choices:
      raise UserError(f"savi.{field}={value!r} is not one of {choices}; set --config.savi.{field} to one of them.")
  if int(c.num_iterations) < 1 or int(c.get("first_frame_iterations", 0)) < 0:
    raise UserError(f"savi.num_iterations={c.num_iterations} must be >= 1 and savi.first_frame_iterations="
                    f"{c.get('first_frame_iterations', 0)} >= 0 (0: as many as num_iterations).")
  pool = savi.input_pool(c)
  if pool < 1 or config.env.resolution % pool:
    raise UserError(f"savi.pool={pool} must be a positive divisor of env.resolution={config.env.resolution}.")
  out = savi.decoder_grid_size(c, config.env.resolution) * math.prod(c.decoder.strides)
  want = config.env.resolution // pool
  if out != want:
    raise UserError(f"the SAVi decoder outputs {out}x{out} images (savi.decoder.grid_size * prod(strides)) but "
                    f"the frames it models are {want}x{want} (env.resolution {config.env.resolution} / savi.pool "
                    f"{pool}); set --config.savi.decoder.grid_size=0 (automatic) or change savi.decoder.strides.")
  rgb_weight, depth_weight = savi.loss_weights(c)
  if rgb_weight < 0 or depth_weight < 0 or rgb_weight + depth_weight <= 0:
    raise UserError(f"savi.train.rgb_weight={rgb_weight} and savi.train.depth_weight={depth_weight} must be >= 0, "
                    "and one of them > 0.")
  devices = jax.local_device_count()
  if c.train.batch_size % devices:
    raise UserError(f"savi.train.batch_size={c.train.batch_size} does not split over {devices} devices; "
                    f"use a multiple of {devices}.")


def make_optimizer(train_config) -> optax.GradientTransformation:
  """Adam on a warmup + cosine-decay schedule, after clipping the gradients' global norm."""
  return optax.chain(optax.clip_by_global_norm(train_config.clip_norm), optax.adam(_schedule(train_config)))


def _schedule(train_config) -> optax.Schedule:
  steps = int(train_config.steps)
  warmup = min(int(train_config.warmup_steps), max(steps - 1, 0))
  return optax.warmup_cosine_decay_schedule(0.0, train_config.learning_rate, warmup, max(steps, warmup + 1), 0.0)


def to_float(video: jax.Array) -> jax.Array:
  """uint8 frames [...] -> float32 in [0, 1], the models' input scaling."""
  return video.astype(jnp.float32) / 255.0


class Compiled:
  """The model, optimizer and jitted functions of a frame-reconstruction model trained on `config.savi.train`.

  model: a Flax module with an `input_pool` attribute whose apply on float video [B, L, H, W, 3] in [0, 1] (rng
  stream "slots" given, used or not) returns recon [B, L, h, w, 3] with h = H / input_pool, and depth [B, L, h, w]
  (metres) when the savi config's depth weight is > 0. SAVi is one; the AE (roboshape/models/ae.py) another.
  """

  def __init__(self, model, savi_config):
    c = savi_config
    self.model = model
    self.optimizer = make_optimizer(c.train)
    self.schedule = _schedule(c.train)
    self.mesh = Mesh(np.array(jax.devices()), ("data",))
    self.replicated = NamedSharding(self.mesh, PartitionSpec())
    self.batch_sharding = NamedSharding(self.mesh, PartitionSpec("data"))
    self.rgb_weight, self.depth_weight = savi.loss_weights(c)
    self.train_step = jax.jit(self._train_step,
                              in_shardings=(self.replicated, self.batch_sharding, self.batch_sharding,
                                            self.replicated),
                              out_shardings=(self.replicated, self.replicated))
    self.eval_video = jax.jit(self._eval_video)

  def init_state(self, key: jax.Array, video_shape: Sequence[int]) -> Dict[str, Any]:
    """The step-0 train state {step, params, opt_state} for clips of shape [B, L, H, W, 3]."""
    params_key, slots_key = jax.random.split(key)
    dummy = jnp.zeros((1, *video_shape[1:]), jnp.float32)
    params = self.model.init({"params": params_key, "slots": slots_key}, dummy)["params"]
    return {"step": jnp.zeros((), jnp.int32), "params": params, "opt_state": self.optimizer.init(params)}

  def _train_step(self, state, video, depth, key):
    """(state, video uint8 [B, L, H, W, 3], depth uint16 [B, L, H, W] mm or None, key) -> (state, metrics).

    The loss is train.rgb_weight (1) times the RGB reconstruction MSE, plus train.depth_weight times the depth MSE
    (in metres) when that weight is > 0 (the model then predicts depth; `depth` must be given). rgb_weight=0 with a
    depth weight trains on depth alone (SAVi++'s target: the slots then group by shape, not by colour).
    """
    step_key = jax.random.fold_in(key, state["step"])

    def loss_fn(params):
      frames = to_float(video)
      target = savi.pool_frames(frames, self.model.input_pool)
      out = self.model.apply({"params": params}, frames, rngs={"slots": step_key})
      terms = {"recon_mse": jnp.mean(jnp.square(out["recon"] - target))}
      loss = self.rgb_weight * terms["recon_mse"]
      if self.depth_weight > 0:
        metres = savi.pool_frames(depth.astype(jnp.float32)[..., None] / 1000.0, self.model.input_pool)[..., 0]
        terms["depth_mse"] = jnp.mean(jnp.square(out["depth"] - metres))
        loss = loss + self.depth_weight * terms["depth_mse"]
      return loss, terms

    (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"])
    updates, opt_state = self.optimizer.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    metrics = {"loss": loss, **terms, "grad_norm": optax.tree.norm(grads), "lr": self.schedule(state["step"])}
    return {"step": state["step"] + 1, "params": params, "opt_state": opt_state}, metrics

  def _eval_video(self, params, video):
    """video uint8 [B, T, H, W, 3] -> the model's outputs."""
    return self.model.apply({"params": params}, to_float(video))


class _SaviCompiled(Compiled):
  """SAVi's: evaluation starts from the frozen encoder's deterministic first-frame slots."""

  def initial_slots(self, params, batch_size: int) -> jax.Array:
    """The frozen encoder's deterministic first-frame slots [B, K, D] (the same for every episode)."""
    noise = jax.random.normal(jax.random.key(INIT_SLOTS_SEED), (self.model.num_slots, self.model.slot_size))
    slots = self.model.apply({"params": params}, noise, method=savi.SAVi.initial_slots)
    return jnp.broadcast_to(slots, (batch_size, *slots.shape))

  def _eval_video(self, params, video):
    """video uint8 [B, T, H, W, 3] -> the model's outputs from the deterministic first-frame slots."""
    init = self.initial_slots(params, video.shape[0])
    return self.model.apply({"params": params}, to_float(video), init_slots=init)


def config_from_json(text: str):
  """A ConfigDict from its JSON (the form configs are cached by)."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  return ml_collections.ConfigDict(json.loads(text))


@functools.lru_cache(maxsize=8)
def _compiled_for(savi_json: str, resolution: int) -> _SaviCompiled:
  c = config_from_json(savi_json)
  return _SaviCompiled(savi.build_model(c, resolution), c)


def compiled(config) -> _SaviCompiled:
  """The (cached) model and jitted functions for `config.savi` at `config.env.resolution`."""
  return _compiled_for(config.savi.to_json(sort_keys=True), int(config.env.resolution))


def evaluate(comp: _SaviCompiled, params, episodes: Sequence[Dict[str, np.ndarray]], eval_config,
             figure_path: Optional[str] = None, title: str = "") -> Dict[str, float]:
  """FG-ARI and matched mIoU of the slot masks on whole (first `eval_config.frames` frames of) episodes.

  fg_ari scores each video as one clustering, so a slot that changes object between frames counts against it (the
  bar); fg_ari_frames is the mean over frames of each frame's own FG-ARI, the decomposition without that consistency.

  Masks of a pooled model (savi.pool = f) are compared at the segmentation's resolution, each mask pixel repeated
  f x f; the reconstruction error is against the pooled frames.

  episodes: dicts with image uint8 [S, H, W, 3] and segmentation uint8 [S, H, W]. Writes the decomposition figure
  of the first episode to `figure_path` when given.
  """
  pool = comp.model.input_pool
  aris, frame_aris, ious, mses = [], [], [], []
  for i, episode in enumerate(episodes):
    video = episode["image"][:eval_config.frames]
    out = jax.device_get(comp.eval_video(params, video[None]))
    seg = ids.robot_as_one(episode["segmentation"][:eval_config.frames])   # the robot is one object
    masks = decomposition.upsample_masks(out["masks"][0], pool)         # at the segmentation's resolution
    aris.append(decomposition.fg_ari(seg, masks, eval_config.background_ids))
    frame_aris.extend(decomposition.fg_ari(seg[t:t + 1], masks[t:t + 1], eval_config.background_ids)
                      for t in range(len(seg)))
    ious.append(decomposition.matched_miou(seg, masks, eval_config.background_ids))
    frames = np.asarray(savi.pool_frames(video.astype(np.float32) / 255.0, pool))
    mses.append(float(np.mean((out["recon"][0] - frames) ** 2)))
    if i == 0 and figure_path:
      n = eval_config.figure_frames
      decomposition.decomposition_figure(frames[:n], out["recon"][0, :n], out["rgb"][0, :n], out["masks"][0, :n],
                                         figure_path, title)
  with np.errstate(all="ignore"):
    return {"fg_ari": float(np.nanmean(aris)) if aris else float("nan"),
            "fg_ari_frames": float(np.nanmean(frame_aris)) if frame_aris else float("nan"),
            "miou": float(np.nanmean(ious)) if ious else float("nan"),
            "recon_mse": float(np.mean(mses)) if mses else float("nan")}


@dataclasses.dataclass(frozen=True)
class Validation:
  """What `fit` does every savi.eval.every steps (and after the last).

  Attributes:
    run: (params, step) -> metrics {name: float}, written to TensorBoard (val/<name>) and <root>/val_metrics.json.
    keys: the metrics <root>/val_metrics.png draws against the step.
    describe: metrics -> the line printed after "[pretrain] step <step>: ".
    ylim: the curve's y range (None: automatic).
  """
  run: Callable[[Any, int], Dict[str, float]]
  keys: Sequence[str]
  describe: Callable[[Dict[str, float]], str]
  ylim: Optional[Tuple[Optional[float], Optional[float]]] = None


def train(config, workdir: str, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
          val_episodes: Sequence[Dict[str, np.ndarray]] = ()) -> Dict[str, Any]:
  """Trains SAVi to `config.savi.train.steps`, resuming from the latest checkpoint in <workdir>/savi/checkpoints.

  batches_from(start_batch) yields the batches from index start_batch on (dicts with video uint8 [B, L, H, W, 3]
  and episode_seed int [B], and depth uint16 [B, L, H, W] when savi.train.depth_weight > 0).
  val_episodes: dicts with image uint8 [S, H, W, 3] and segmentation uint8 [S, H, W], scored by `evaluate`.
  Returns {"step", "params", "history": [(step, loss)], "eval": [(step, metrics)]}.
  """
  validate_config(config)
  comp, ec = compiled(config), config.savi.eval
  root = savi_dir(workdir)
  validation = None
  if val_episodes:
    validation = Validation(
        run=lambda params, step: evaluate(comp, params, val_episodes[:ec.episodes], ec,
                                          os.path.join(root, "figures", f"step_{step:07d}.png"),
                                          f"{config.name} step {step}"),
        keys=("fg_ari", "fg_ari_frames", "miou"), ylim=(None, 1.0),
        describe=lambda r: (f"val FG-ARI {r['fg_ari']:.3f} (per frame {r['fg_ari_frames']:.3f}) mIoU "
                            f"{r['miou']:.3f} recon MSE {r['recon_mse']:.5f}"))
  return fit(config, root, comp, batches_from, validation, "SAVi")


def fit(config, root: str, comp: Compiled, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
        validation: Optional[Validation], title: str) -> Dict[str, Any]:
  """Trains `comp.model` to `config.savi.train.steps` by `comp.train_step`, resuming from <root>/checkpoints.

  Every setting comes from config.savi.train (clip shape, steps, checkpoint and log cadence) and config.savi.eval
  (validation cadence); TensorBoard scalars go to <root>/tb, validation results to <root>/val_metrics.json.
  batches_from: as in `train`. validation: None for none. title: the model's name in messages ("SAVi").
  Returns {"step", "params", "history": [(step, loss)], "eval": [(step, metrics)]}.
  """
  # pylint: disable=import-outside-toplevel
  from tensorboardX import SummaryWriter
  from tqdm import tqdm

  tc, ec = config.savi.train, config.savi.eval
  history, evals = [], []
  with Checkpointer(os.path.join(root, "checkpoints"), keep=tc.keep_checkpoints) as ckpt:
    start = ckpt.latest_step() or 0
    if start >= tc.steps:
      restored, start = ckpt.restore_latest(_abstract_state(comp, config), set_aside=True)
      if start >= tc.steps:
        print(f"[pretrain] already trained to step {start} >= savi.train.steps={tc.steps}; skipping.", flush=True)
        return {"step": start, "params": restored["params"], "history": history, "eval": evals}
    key = jax.random.key(config.seed)
    state = jax.device_put(comp.init_state(jax.random.fold_in(key, 1), _clip_shape(config)), comp.replicated)
    if start:
      state, start = ckpt.resume(state)     # the newest step that restores; damaged newer ones are set aside
      print(f"[pretrain] resuming from step {start}", flush=True)
    step_key = jax.random.fold_in(key, 2)
    seconds_before, run_start = history_lib.seconds_at(root, "val_metrics", start), time.perf_counter()
    writer = SummaryWriter(os.path.join(root, "tb"))
    batches = batches_from(start)
    try:
      for step in tqdm(range(start, tc.steps), initial=start, total=tc.steps, desc=f"pretrain {title}",
                       smoothing=0.1):
        batch = next(batches)
        if step == start and tuple(np.shape(batch["video"])) != _clip_shape(config):
          raise UserError(f"the dataset's clips have shape {tuple(np.shape(batch['video']))}, the {title} config "
                          f"expects {_clip_shape(config)} [B, L, H, W, 3]: set --config.env.resolution to the "
                          "dataset's.")
        if step == start and comp.depth_weight > 0 and "depth" not in batch:
          raise UserError("savi.train.depth_weight > 0 needs a dataset with depth: collect one with "
                          "--config.env.depth=True (into another --config.data.dir), or set the weight to 0.")
        video = jax.make_array_from_process_local_data(comp.batch_sharding, np.asarray(batch["video"]))
        depth = None
        if comp.depth_weight > 0:
          depth = jax.make_array_from_process_local_data(comp.batch_sharding, np.asarray(batch["depth"]))
        new_state, metrics = comp.train_step(state, video, depth, step_key)
        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        if not np.isfinite(metrics["loss"]):
          ckpt.wait()
          raise UserError(
              f"{title} loss is {metrics['loss']} at step {step} (batch {step}, episode seeds "
              f"{np.asarray(batch['episode_seed']).tolist()}); training stopped, the last good checkpoint "
              f"(step {ckpt.latest_step()}) is kept in {ckpt.directory}. Lower --config.savi.train.learning_rate "
              f"or --config.savi.train.clip_norm and run again.")
        state, done = new_state, step + 1
        history.append((done, metrics["loss"]))
        if done % tc.log_every == 0 or done == tc.steps:
          for name, value in metrics.items():
            writer.add_scalar(f"train/{name}", value, done)
        if done % tc.checkpoint_every == 0 or done == tc.steps:
          ckpt.save(done, state)
        if validation and (done % ec.every == 0 or done == tc.steps):
          result = validation.run(state["params"], done)
          for name, value in result.items():
            writer.add_scalar(f"val/{name}", value, done)
          evals.append((done, result))
          history_lib.record(root, "val_metrics", done, result, seconds_before + time.perf_counter() - run_start,
                             keys=validation.keys, title=f"{title} validation, {config.name}", ylim=validation.ylim)
          tqdm.write(f"[pretrain] step {done}: {validation.describe(result)}")
    finally:
      writer.close()
  return {"step": int(state["step"]), "params": state["params"], "history": history, "eval": evals}


def _clip_shape(config):
  r = config.env.resolution
  return (config.savi.train.batch_size, config.savi.train.clip_length, r, r, 3)


def _with_sharding(tree, sharding):
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), tree)


def _abstract_state(comp: Compiled, config):
  """The shapes, dtypes and (replicated) shardings of the train state {step, params, opt_state}."""
  like = jax.eval_shape(lambda: comp.init_state(jax.random.key(0), _clip_shape(config)))
  return _with_sharding(like, comp.replicated)


def restore_latest(config, workdir: str, comp: Compiled, directory: str, title: str) -> Tuple[Any, int]:
  """(params, step) of the newest checkpoint in `directory` that restores (a damaged newer one is skipped with a
  one-line warning); a UserError saying how to make one when there is none.

  config and workdir: the run's (for the message); comp: the model the checkpoint holds the train state of.
  """
  ckpt = Checkpointer(directory)
  try:
    if ckpt.latest_step() is None:
      raise UserError(f"no {title} checkpoint in {directory}; run the pretrain stage first "
                      f"(python launch.py --config=configs/{config.name}.py --workdir={workdir}).")
    state, step = ckpt.restore_latest(_abstract_state(comp, config))
    return state["params"], step
  finally:
    ckpt.close()


def data_source(config, workdir: str):
  """(batches_from, val_episodes) of the run's dataset (roboshape.data) for `fit`: clips of config.savi.train's
  shape from the train split (batch i always the same), and the first config.savi.eval.episodes val episodes."""
  # pylint: disable=import-outside-toplevel
  from roboshape import data as rdata
  from roboshape.data import reader

  path = rdata.dataset_path(config, workdir)
  reader.load_state(path)  # a missing dataset is a UserError that says how to make one
  tc = config.savi.train

  def batches_from(start: int):
    return reader.clip_batches(path, "train", tc.clip_length, tc.batch_size, seed=config.seed, start_batch=start)

  return batches_from, list(itertools.islice(reader.read_episodes(path, "val"), config.savi.eval.episodes))


def run(config, workdir: str) -> None:
  """The pretrain stage: trains SAVi on the dataset of `config` (roboshape.data) to config.savi.train.steps."""
  result = train(config, workdir, *data_source(config, workdir))
  if result["eval"]:
    step, metrics = result["eval"][-1]
    print(f"[pretrain] step {step}: val FG-ARI {metrics['fg_ari']:.3f}, mIoU {metrics['miou']:.3f}", flush=True)


def _frozen_step(model: savi.SAVi, params, state, frames):
  """FrozenEncoder step: (params, state, frames uint8 [B, H, W, 3]) -> (slots [B, K, D], next state).

  state: dict(slots=the predicted slots [B, K, D], first=bool [B], True where the frame starts an episode). A model
  with its own number of first-frame iterations runs them, only in a batch that has a first frame in it (on the
  same encoder features).
  """
  features = model.apply({"params": params}, to_float(frames), method=savi.SAVi.encode_frame)
  apply = functools.partial(model.apply, {"params": params}, features, state["slots"], method=savi.SAVi.correct)
  later = apply(first=False)
  if model.iterations_first != model.num_iterations:
    first = state["first"][:, None, None]
    def with_first(later):
      return jax.tree.map(lambda a, b: jnp.where(first, a, b), apply(first=True), later)
    later = jax.lax.cond(jnp.any(state["first"]), with_first, lambda later: later, later)
  slots, predicted = later
  return slots, {"slots": predicted, "first": jnp.zeros_like(state["first"])}




def load_encoder(workdir: str) -> FrozenEncoder:
  """The SAVi encoder trained in `workdir` (its latest checkpoint), frozen: tokens are a frame's K slots [B, K, D].

  The state is dict(slots=the predicted slots for the next frame [B, K, D], first=bool [B]); `init_state(B)` gives
  the learned-Gaussian slots drawn with a fixed key (so encoding is deterministic and the same for every episode of
  a batch) and first=True.
  """
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  config = stages.load_config(workdir)
  comp = compiled(config)
  directory = os.path.join(savi_dir(workdir), "checkpoints")
  params, step = restore_latest(config, workdir, comp, directory, "SAVi")
  init = comp.initial_slots(params, 1)[0]
  return FrozenEncoder(
      name="savi", params=params, step=functools.partial(_frozen_step, comp.model),
      init_state=lambda batch_size: {"slots": jnp.broadcast_to(init, (batch_size, *init.shape)),
                                     "first": jnp.ones((batch_size,), bool)},
      num_tokens=comp.model.num_slots, token_dim=comp.model.slot_size,
      identity=f"savi:{os.path.abspath(directory)}@{step}")
