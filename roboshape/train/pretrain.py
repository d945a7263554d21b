"""The "pretrain" stage: one training loop for every encoder pretrained in the run's workdir (SAVi, the AE, ...).

  python launch.py --config=configs/pick_savi.py:small --config.stages='("pretrain",)' --workdir=runs/pick_savi
  enc = roboshape.load_encoder("runs/pick_savi")      # the encoder, served from what this stage trained

The model is chosen by the run's encoder name: its registration (roboshape/encoders, `Kind.model`) says how the
model is built from the config, what it minimises (the reconstruction MSE below unless it says otherwise) and how
the best of several seeds is chosen, and its own config section describes it (config.savi, config.ae). The rest is
this module's and the same for every model, so they are pretrained alike:

Settings: config.pretrain, one section for every model (configs/common.py:pretrain_config says why).
Training: clips of pretrain.train.clip_length frames from the dataset's train split, the reconstruction MSE against
the frames pooled by the model's input_pool (plus pretrain.train.depth_weight x the depth MSE; with
pretrain.train.mask_weight = p > 0 each pixel's error weighs (its segment's share of the frame)^-p, `mask_weights`,
so small objects count for more: it reads the simulator's segmentation in pretraining only), Adam with linear
warmup, cosine decay and global-norm clipping (`make_optimizer`). The jitted train step shards the batch over the
devices of a 1-D mesh ("data") and keeps parameters replicated. Writes under <workdir>/<encoder>/: checkpoints/
(orbax; resumed after a kill at the same step, with the same data order since batch i of the dataset's
deterministic order always feeds step i), tb/ (TensorBoard scalars: loss, recon_mse, grad_norm, lr, and the
validation's metrics), val_metrics.json and val_metrics.png (every validation result so far, across resumes, and
its curve). A non-finite loss or gradient norm stops training at once with the step and the batch's episode seeds
(roboshape/train/divergence.py, as behaviour cloning does): no checkpoint of non-finite parameters is written, the
last one stays, and the stage is not done.

Seeds (`train_and_select`, what the stage runs): with pretrain.train_seeds = () one run with config.seed writes the
above into <workdir>/<encoder>/ itself. With pretrain.train_seeds = (s1, s2, ...) each seed is a run of its own,
with config.seed set to it (its initialisation and its data order), in <workdir>/<encoder>/seed_<s>/ (the layout
above, each resumed after a kill as one run is); once every seed is trained, the one with the best FINAL validation
of the model's selection metric (the last evaluation in its val_metrics.json, the one at its last training step;
ties: the lower seed; a NaN ranks last) is recorded in <workdir>/<encoder>/selected.json with every seed's final
metrics, and <workdir>/<encoder>/seeds_<metric>.png overlays every seed's curve of it. The encoder's module serves
the selected seed's checkpoint (roboshape/encoders/savi.py).

Validation is not this module's: `train` and `run` take `make_validation(config, root, model, episodes) ->
Validation`, which the stage wiring (roboshape/stages.py) takes from the encoder's evaluator (SAVi's
roboshape/eval/slots.py: FG-ARI and mIoU of the slot masks and the decomposition figures in figures/; the AE's
roboshape/eval/reconstruction.py).
"""
import dataclasses
import functools
import itertools
import json
import os
import time
from typing import Any, Callable, Dict, Iterator, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from roboshape import encoders
from roboshape.envs import ids
from roboshape import fileio
from roboshape import progress
from roboshape import ranges
from roboshape import rundir
from roboshape.checkpoint import Checkpointer
from roboshape.errors import UserError
from roboshape.models import savi
from roboshape.train import divergence
from roboshape.train import history as history_lib
from roboshape.train import scalars
from roboshape.train import sharding


def model_of(config) -> encoders.PretrainModel:
  """The model the run's encoder pretrains (its registration's `model`); a UserError for an encoder without one."""
  kind = encoders.get(config.encoder)
  if kind.model is None:
    raise UserError(f"the {kind.name} encoder has no pretrain stage; drop it from --config.stages.")
  return kind.model


def validate_config(config) -> None:
  """Raises UserError when the encoder's own section cannot work with the env's resolution: its registration's
  `check`, which roboshape/config_check.py also runs before any stage."""
  kind = encoders.get(config.encoder)
  if kind.check is not None:
    kind.check(config)


SAVI_CLIP_NORM = 0.05   # SAVi's max_grad_norm (on its loss, summed over a clip's pixel values)
ADAM_EPS = 1e-8         # Adam's epsilon (optax's and SAVi's) at that clip
CLIP_NORM_OF = ("mean", "sum")   # pretrain.train.clip_norm_of: the loss whose gradient pretrain.train.clip_norm bounds

# The ranges of the pretrain section, read by every encoder with a pretrain stage (Kind.sections).
RANGES = (
    ranges.Int("pretrain.train.steps", 0, "pretraining steps"),
    ranges.Int("pretrain.train.batch_size", 1, "clips per step"),
    ranges.Int("pretrain.train.clip_length", 1, "frames per clip"),
    ranges.Int("pretrain.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
    ranges.Int("pretrain.train.checkpoint_every", 1, "steps between checkpoints"),
    ranges.Int("pretrain.train.keep_checkpoints", 1, "checkpoints kept"),
    ranges.Int("pretrain.train.log_every", 1, "steps between TensorBoard logs"),
    ranges.Number("pretrain.train.learning_rate", 0.0, "the peak learning rate", low_ok=False),
    ranges.Number("pretrain.train.clip_norm", 0.0, "the global gradient-norm clip", low_ok=False),
    ranges.Number("pretrain.train.depth_weight", 0.0, "the weight of the depth MSE; 0: no depth target"),
    ranges.Number("pretrain.train.mask_weight", 0.0, "p: a pixel's error weighs its segment's share of the frame to "
                  "the power -p; 0: every pixel alike", high=2.0),
    ranges.Choice("pretrain.train.clip_norm_of", CLIP_NORM_OF,
                  "the loss whose gradient clip_norm bounds: the mean over a clip's values, or their sum (SAVi's)"),
    ranges.Int("pretrain.eval.every", 1, "steps between validations"),
    ranges.Int("pretrain.eval.episodes", 0, "validation episodes; 0: no validation"),
    ranges.Int("pretrain.eval.frames", 1, "frames of each validation episode"),
    ranges.Ints("pretrain.train_seeds", 0, "one pretraining run per seed, the best by validation kept; (): one run "
                "with config.seed", empty_ok=True, distinct=True),
)


def check_config(config) -> None:
  """Raises UserError for the first bad field of the pretrain section: RANGES, seeds that can be ranked, and depth
  in the data for a depth target (roboshape/config_check.py runs it before any stage, for an encoder with a
  pretrain stage)."""
  ranges.check(config, RANGES)
  p = config.pretrain
  if len(p.train_seeds) > 1 and p.eval.episodes < 1:
    raise UserError(f"pretrain.train_seeds={tuple(p.train_seeds)!r} selects a seed by validation, which "
                    f"pretrain.eval.episodes={p.eval.episodes} turns off: set pretrain.eval.episodes >= 1, or train "
                    "one seed.")
  weight = float(p.train.depth_weight)
  if weight > 0 and not config.env.depth and {"collect", "pretrain"} & set(config.stages):
    raise UserError(f"pretrain.train.depth_weight={weight} needs depth in the dataset: set "
                    "--config.env.depth=True, or --config.pretrain.train.depth_weight=0.")


def values_per_clip(config, input_pool: int) -> int:
  """The pixel values the loss averages over in one clip: clip_length x h x w x 3, with h = w = env.resolution /
  input_pool, the side of the frames the model reconstructs."""
  side = int(config.env.resolution) // int(input_pool)
  return int(config.pretrain.train.clip_length) * side * side * 3


def clip_norm(train_config, values: int) -> float:
  """The bound on the global norm of the MEAN loss's gradient that train.clip_norm states: itself with
  train.clip_norm_of = "mean"; with "sum" (a bound on the gradient of the loss summed over the clip's `values`
  pixel values, which is `values` times larger) divided by `values`."""
  clip = float(train_config.clip_norm)
  return clip / values if train_config.clip_norm_of == "sum" else clip


def make_optimizer(train_config, values: int) -> optax.GradientTransformation:
  """Adam on a warmup + cosine-decay schedule, after clipping the gradients' global norm to `clip_norm`.

  The clip applies to the gradient of the loss as `Compiled` reduces it: a mean over the clip's `values` pixel
  values. Adam's epsilon scales with the clip (ADAM_EPS at SAVI_CLIP_NORM, so 1e-8 at 0.05), which makes a clip
  scaled together with the loss give the same updates: Adam is blind to the gradients' scale except through
  epsilon. So SAVi's 0.05 on its loss summed over the values (clip_norm_of="sum") gives SAVi's updates.
  """
  clip = clip_norm(train_config, values)
  eps = ADAM_EPS * (clip / SAVI_CLIP_NORM)   # exactly ADAM_EPS at clip 0.05
  return optax.chain(optax.clip_by_global_norm(clip), optax.adam(make_schedule(train_config), eps=eps))


def make_schedule(train_config) -> optax.Schedule:
  """Linear warmup from 0 to the learning rate, then cosine decay to 0 at the last step."""
  steps = int(train_config.steps)
  warmup = min(int(train_config.warmup_steps), max(steps - 1, 0))
  return optax.warmup_cosine_decay_schedule(0.0, train_config.learning_rate, warmup, max(steps, warmup + 1), 0.0)


def mask_weights(segmentation: np.ndarray, power: float) -> np.ndarray:
  """float32 [..., H, W] pixel weights of segmentation [..., H, W] (the robot's links as one segment,
  roboshape/envs/ids.py): a pixel weighs (the share of its frame its segment covers)^-power, scaled so that each
  frame's weights average 1. power 1 gives every segment of a frame the same total weight, however small."""
  seg = ids.robot_as_one(np.asarray(segmentation))
  flat = seg.reshape(-1, seg.shape[-2] * seg.shape[-1]).astype(np.int64)
  counts = np.stack([np.bincount(f, minlength=256)[f] for f in flat]).astype(np.float64)
  weight = (counts / flat.shape[1]) ** -float(power)
  weight /= weight.mean(axis=1, keepdims=True)
  return weight.reshape(seg.shape).astype(np.float32)


def reconstruction_loss(model, out, frames, depth, depth_weight: float, pixel_weight=None):
  """(loss, {term: value}) of a frame model's outputs `out` on float frames [B, L, H, W, 3] in [0, 1]: the RGB
  reconstruction MSE against the frames pooled by model.input_pool, a mean over clips, frames, pixels and channels
  (SAVi's is the sum over a clip's frames, pixels and channels, meaned over clips; train.clip_norm_of says which
  one the clip is stated for), plus `depth_weight` times the depth MSE in metres when that weight is > 0 (the model
  then predicts depth, SAVi++'s second target; depth uint16 [B, L, H, W] millimetres must be given). With
  `pixel_weight` [B, L, H, W] (`mask_weights`, mean 1 a frame) each pixel's squared errors are weighted by it, pooled
  as the frames are; recon_mse stays the plain MSE, so runs with and without weights read alike."""
  target = savi.pool_frames(frames, model.input_pool)
  error = jnp.square(out["recon"] - target)
  terms = {"recon_mse": jnp.mean(error)}
  loss = terms["recon_mse"]
  if pixel_weight is not None:
    pooled = savi.pool_frames(pixel_weight[..., None], model.input_pool)
    loss = terms["weighted_mse"] = jnp.mean(pooled * error)
  if depth_weight > 0:
    metres = savi.pool_frames(depth.astype(jnp.float32)[..., None] / 1000.0, model.input_pool)[..., 0]
    terms["depth_mse"] = jnp.mean(jnp.square(out["depth"] - metres))
    loss = loss + depth_weight * terms["depth_mse"]
  return loss, terms


class _TrainStep:
  """A jitted train step whose last argument, the pixel weights, may be left out (jit's in_shardings name every
  positional argument, so it is always passed, None when absent). `lower` as jax.jit's; `__wrapped__` the step."""

  def __init__(self, step, in_shardings, out_shardings):
    self.__wrapped__ = step
    self._jitted = jax.jit(step, in_shardings=in_shardings, out_shardings=out_shardings)

  def __call__(self, state, video, depth, first, key, pixel_weight=None):
    return self._jitted(state, video, depth, first, key, pixel_weight)

  def lower(self, state, video, depth, first, key, pixel_weight=None):
    return self._jitted.lower(state, video, depth, first, key, pixel_weight)


class Compiled:
  """The model, optimizer and jitted train step of a run's pretraining: the model its encoder names (`model_of`),
  trained on `config.pretrain.train` by its loss (`reconstruction_loss` unless it names another)."""

  def __init__(self, model, config):
    tc = config.pretrain.train
    self.model = model
    self.loss = model_of(config).loss or reconstruction_loss
    self.optimizer = make_optimizer(tc, values_per_clip(config, model.input_pool))
    self.schedule = make_schedule(tc)
    self.dp = sharding.DataParallel(tc.batch_size)
    self.depth_weight = savi.depth_weight(config)
    self.conditional = savi.conditional(model)     # its first slots come from the first frame's cues
    self.mask_weight = float(tc.mask_weight)
    self.train_step = _TrainStep(self._train_step,
                                 in_shardings=(self.dp.replicated, self.dp.batch, self.dp.batch, self.dp.batch,
                                               self.dp.replicated, self.dp.batch),
                                 out_shardings=(self.dp.replicated, self.dp.replicated))

  def init_state(self, key: jax.Array, video_shape: Sequence[int]) -> Dict[str, Any]:
    """The step-0 train state {step, params, opt_state} for clips of shape [B, L, H, W, 3], built by one compiled
    call (run op by op, the model's initialisation compiles each of its hundreds of small operations apart)."""
    def build(key):
      params_key, slots_key = jax.random.split(key)
      dummy = jnp.zeros((1, *video_shape[1:]), jnp.float32)
      params = self.model.init({"params": params_key, "slots": slots_key}, dummy)["params"]
      return {"step": jnp.zeros((), jnp.int32), "params": params, "opt_state": self.optimizer.init(params)}
    return jax.jit(build)(key)

  def _train_step(self, state, video, depth, first_segmentation, key, pixel_weight=None):
    """(state, video uint8 [B, L, H, W, 3], depth uint16 [B, L, H, W] mm or None, the clips' first segmentation
    [B, H, W] as the slots see it (a conditional SAVi's cues) or None, key, the pixels' loss weights [B, L, H, W]
    (`mask_weights`) or None) -> (state, metrics)."""
    step_key = jax.random.fold_in(key, state["step"])
    cues = {} if first_segmentation is None else {
        "cues": savi.first_frame_cues(first_segmentation, self.model.num_slots)}

    def loss_fn(params):
      frames = savi.to_float(video)
      out = self.model.apply({"params": params}, frames, rngs={"slots": step_key}, **cues)
      weighted = {} if pixel_weight is None else {"pixel_weight": pixel_weight}
      return self.loss(self.model, out, frames, depth, self.depth_weight, **weighted)

    (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"])
    updates, opt_state = self.optimizer.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    metrics = {"loss": loss, **terms, "grad_norm": optax.tree.norm(grads), "lr": self.schedule(state["step"])}
    return {"step": state["step"] + 1, "params": params, "opt_state": opt_state}, metrics


def config_from_json(text: str):
  """A ConfigDict from its JSON (the form configs are cached by)."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  return ml_collections.ConfigDict(json.loads(text))


def compile_key(config) -> str:
  """The config as JSON without config.seed and pretrain.train_seeds (which run trains, not how one trains): the
  cache key of the compiled model and train step, the same for every seed."""
  tree = config.to_dict()
  tree.pop("seed", None)
  tree.get("pretrain", {}).pop("train_seeds", None)
  return json.dumps(tree, sort_keys=True)


@functools.lru_cache(maxsize=8)
def _compiled_for(key: str) -> Compiled:
  config = config_from_json(key)
  return Compiled(model_of(config).build(config), config)


def compiled(config) -> Compiled:
  """The (cached) model of the run's encoder and its jitted train step for `config`."""
  return _compiled_for(compile_key(config))


@dataclasses.dataclass(frozen=True)
class Validation:
  """What `fit` does every pretrain.eval.every steps (and after the last).

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


# make_validation(config, root, model, val_episodes) -> Validation: what validates a model during pretraining.
MakeValidation = Callable[[Any, str, Any, Sequence[Dict[str, np.ndarray]]], Validation]


def train(config, workdir: str, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
          val_episodes: Sequence[Dict[str, np.ndarray]] = (),
          make_validation: Optional[MakeValidation] = None, root: Optional[str] = None) -> Dict[str, Any]:
  """Trains the run's encoder's model to `config.pretrain.train.steps`, resuming from the latest checkpoint in
  <root>/checkpoints (root: <workdir>/<encoder> when None; `train_and_select` gives each seed's folder).

  batches_from(start_batch) yields the batches from index start_batch on (dicts with video uint8 [B, L, H, W, 3]
  and episode_seed int [B], and depth uint16 [B, L, H, W] when pretrain.train.depth_weight > 0).
  val_episodes: dicts with image uint8 [S, H, W, 3] and segmentation uint8 [S, H, W] (and depth uint16 [S, H, W]),
  validated by the Validation `make_validation` makes (e.g. roboshape.eval.slots.validation); none without either.
  Returns {"step", "params", "history": [(step, loss)], "eval": [(step, metrics)]}.
  """
  validate_config(config)
  comp, root = compiled(config), root or rundir.pretrain_dir(workdir, config.encoder)
  validation = None
  if val_episodes and make_validation is not None:
    validation = make_validation(config, root, comp.model, val_episodes)
  return fit(config, root, comp, batches_from, validation, encoders.get(config.encoder).title)


def fit(config, root: str, comp: Compiled, batches_from: Callable[[int], Iterator[Dict[str, np.ndarray]]],
        validation: Optional[Validation], title: str) -> Dict[str, Any]:
  """Trains `comp.model` to `config.pretrain.train.steps` by `comp.train_step`, resuming from <root>/checkpoints.

  Every setting comes from config.pretrain.train (clip shape, steps, checkpoint and log cadence) and
  config.pretrain.eval (validation cadence); TensorBoard scalars go to <root>/tb, validation results to
  <root>/val_metrics.json.
  batches_from: as in `train`. validation: None for none. title: the model's name in messages ("SAVi").
  Returns {"step", "params", "history": [(step, loss)], "eval": [(step, metrics)]}.
  """
  from tqdm import tqdm  # pylint: disable=import-outside-toplevel

  tc, ec = config.pretrain.train, config.pretrain.eval
  history, evals = [], []
  with Checkpointer(rundir.checkpoints(root), keep=tc.keep_checkpoints) as ckpt:
    start = ckpt.latest_step() or 0
    if start >= tc.steps:
      restored, start = ckpt.restore_latest(_abstract_state(comp, config), set_aside=True)
      if start >= tc.steps:
        print(f"[pretrain] already trained to step {start} >= pretrain.train.steps={tc.steps}; skipping.",
              flush=True)
        if validation and not any(h["step"] == start for h in history_lib.load(root, "val_metrics")):
          # killed after its last checkpoint, before its last validation: the final evaluation is still owed
          evals.append((start, _validate(validation, restored["params"], start, root, config, title,
                                         history_lib.seconds_at(root, "val_metrics", start))))
        return {"step": start, "params": restored["params"], "history": history, "eval": evals}
    key = jax.random.key(config.seed)
    state = jax.device_put(comp.init_state(jax.random.fold_in(key, 1), _clip_shape(config)), comp.dp.replicated)
    if start:
      state, start = ckpt.resume(state)     # the newest step that restores; damaged newer ones are set aside
      print(f"[pretrain] resuming from step {start}", flush=True)
    step_key = jax.random.fold_in(key, 2)
    fields = {"pretrain.train.learning_rate": tc.learning_rate, "pretrain.train.clip_norm": tc.clip_norm}
    seconds_before, run_start = history_lib.seconds_at(root, "val_metrics", start), time.perf_counter()
    writer = scalars.Scalars(os.path.join(root, "tb"))
    batches = batches_from(start)
    try:
      for step in progress.bar(range(start, tc.steps), initial=start, total=tc.steps, desc=f"pretrain {title}",
                       smoothing=0.1):
        batch = next(batches)
        if step == start and tuple(np.shape(batch["video"])) != _clip_shape(config):
          raise UserError(f"the dataset's clips have shape {tuple(np.shape(batch['video']))}, the {title} config "
                          f"expects {_clip_shape(config)} [B, L, H, W, 3]: set --config.env.resolution to the "
                          "dataset's.")
        if step == start and comp.depth_weight > 0 and "depth" not in batch:
          raise UserError("pretrain.train.depth_weight > 0 needs a dataset with depth: collect one with "
                          "--config.env.depth=True (into another --config.data.dir), or set the weight to 0.")
        video = comp.dp.put_batch(batch["video"])
        depth = comp.dp.put_batch(batch["depth"]) if comp.depth_weight > 0 else None
        first = comp.dp.put_batch(ids.robot_as_one(batch["segmentation"][:, 0])) if comp.conditional else None
        weight = None if comp.mask_weight <= 0 else comp.dp.put_batch(
            mask_weights(batch["segmentation"], comp.mask_weight))
        new_state, metrics = comp.train_step(state, video, depth, first, step_key, weight)
        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        state, done = new_state, step + 1
        divergence.check({"loss": metrics["loss"], "gradient norm": metrics["grad_norm"]}, done, ckpt,
                         stage="pretrain", what=f"the {title}", fields=fields,
                         detail=f" (batch {step}, episode seeds {np.asarray(batch['episode_seed']).tolist()})")
        history.append((done, metrics["loss"]))
        if done % tc.log_every == 0 or done == tc.steps:
          writer.write(done, {f"train/{name}": value for name, value in metrics.items()})
        if done % tc.checkpoint_every == 0 or done == tc.steps:
          divergence.check_params(state["params"], done, ckpt, stage="pretrain", what=f"the {title}'s",
                                  fields=fields)
          ckpt.save(done, state)
        if validation and (done % ec.every == 0 or done == tc.steps):
          evals.append((done, _validate(validation, state["params"], done, root, config, title,
                                        seconds_before + time.perf_counter() - run_start, writer, tqdm.write)))
    finally:
      writer.close()
  return {"step": int(state["step"]), "params": state["params"], "history": history, "eval": evals}


def _validate(validation: Validation, params, step: int, root: str, config, title: str, seconds: float,
              writer=None, write=print) -> Dict[str, float]:
  """Runs `validation` at `step`: its metrics to TensorBoard (when a writer is given) and <root>/val_metrics.json,
  and one line to `write`; returns the metrics."""
  result = validation.run(params, step)
  if writer is not None:
    writer.write(step, {f"val/{name}": value for name, value in result.items()})
  history_lib.record(root, "val_metrics", step, result, seconds, keys=validation.keys,
                     title=f"{title} validation, {config.name}", ylim=validation.ylim)
  write(f"[pretrain] step {step}: {validation.describe(result)}")
  return result


def _clip_shape(config):
  r = config.env.resolution
  return (config.pretrain.train.batch_size, config.pretrain.train.clip_length, r, r, 3)


def _with_sharding(tree, target):
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=target), tree)


def _abstract_state(comp: Compiled, config):
  """The shapes, dtypes and (replicated) shardings of the train state {step, params, opt_state}."""
  like = jax.eval_shape(lambda: comp.init_state(jax.random.key(0), _clip_shape(config)))
  return _with_sharding(like, comp.dp.replicated)


def data_source(config, workdir: str):
  """(batches_from, val_episodes) of the run's dataset (roboshape.data) for `fit`: clips of config.pretrain.train's
  shape from the train split (batch i always the same), and the first config.pretrain.eval.episodes val
  episodes. With several env.cameras one model learns every view: the clips come from every camera's frames, and
  each of those val episodes is validated in every view (roboshape/envs/camera.py `view`)."""
  # pylint: disable=import-outside-toplevel
  from roboshape import data as rdata
  from roboshape.data import reader
  from roboshape.envs import camera

  path = rdata.dataset_path(config, workdir)
  reader.load_state(path)  # a missing dataset is a UserError that says how to make one
  tc = config.pretrain.train
  cameras = tuple(config.env.cameras)

  def batches_from(start: int):
    return reader.clip_batches(path, "train", tc.clip_length, tc.batch_size, seed=config.seed, start_batch=start,
                               cameras=cameras)

  val = itertools.islice(reader.read_episodes(path, "val"), config.pretrain.eval.episodes)
  return batches_from, [camera.view(e, c) for e in val for c in cameras]


# ----------------------------------------------------------------------------------------------------------------
# Seeds: one run per seed of pretrain.train_seeds, the best by its final validation served.

# source(config) -> (batches_from, val_episodes) of `config`'s seed (its data order): as `data_source`.
Source = Callable[[Any], Tuple[Callable[[int], Iterator[Dict[str, np.ndarray]]], Sequence[Dict[str, np.ndarray]]]]


def with_seed(config, seed: int):
  """A copy of `config` with config.seed = `seed` (what one seed's run trains with)."""
  seeded = config.copy_and_resolve_references()
  seeded.seed = int(seed)
  return seeded


def train_and_select(config, workdir: str, source: Source, make_validation: Optional[MakeValidation] = None
                     ) -> Dict[str, Any]:
  """The pretrain stage's training (see the module's docstring): with pretrain.train_seeds = (), `train` once with
  config.seed in <workdir>/<encoder>/; else `train` for each seed s in turn with config.seed = s in
  <workdir>/<encoder>/seed_<s>/ (each resumes or skips as `fit` does), then `select_seed` by the model's selection.
  source(seed_config) gives each seed its data.

  selected.json is removed before any seed trains and written once all are trained, so it always names a seed
  whose run is finished (a run killed in between serves no encoder until the stage is run again).
  Returns `train`'s result for seeds = (); else {"selected": seed, "selection": selected.json's dict,
  "runs": {seed: `train`'s result}}.
  """
  stage_dir, title = rundir.pretrain_dir(workdir, config.encoder), encoders.get(config.encoder).title

  def train_one(seed_config, root):
    return train(seed_config, workdir, *source(seed_config), make_validation=make_validation, root=root)

  seeds = rundir.train_seeds(config, "pretrain")
  if seeds == (None,):
    return train_one(config, stage_dir)
  path = rundir.selection_path(stage_dir)
  if os.path.exists(path):
    os.remove(path)
  runs = {}
  for seed in seeds:
    print(f"[pretrain] {title} seed {seed} of {seeds} -> {rundir.seed_dir(stage_dir, seed)}", flush=True)
    runs[seed] = train_one(with_seed(config, seed), rundir.seed_dir(stage_dir, seed))
  chosen = select_seed(config, stage_dir, {s: r["step"] for s, r in runs.items()}, model_of(config).selection,
                       title)
  return {"selected": chosen["selected_seed"], "selection": chosen, "runs": runs}


def select_seed(config, stage_dir: str, steps: Dict[int, int], selection: encoders.Selection,
                title: str) -> Dict[str, Any]:
  """Selects among the trained seeds (`steps`: seed -> the step its run ended at) by each one's final validation
  (the last entry of <stage_dir>/seed_<s>/val_metrics.json, which must be at that step): the best
  `selection.metric`, ties to the lower seed, NaN last. Writes <stage_dir>/selected.json and the curves'
  figure <stage_dir>/seeds_<metric>.png; returns the selection: {"selected_seed", "metric", "higher_is_better",
  "seeds": [{"seed", "step", "train_seconds", <every validation metric>}, ...]} in the config's seed order."""
  records, curves = [], {}
  for seed, step in steps.items():
    history = history_lib.load(rundir.seed_dir(stage_dir, seed), "val_metrics")
    if not history or history[-1]["step"] != step or selection.metric not in history[-1]:
      if len(steps) == 1:
        records.append({"seed": seed, "step": step})
        continue
      raise UserError(
          f"{title} seed {seed} has no validation {selection.name} at its last step {step} in "
          f"{rundir.seed_dir(stage_dir, seed)}/val_metrics.json, so pretrain.train_seeds={tuple(steps)} cannot be "
          "ranked: give the run validation episodes (pretrain.eval.episodes >= 1, a dataset with a val split).")
    records.append({"seed": seed, **history[-1]})
    curves[seed] = history

  def rank(record):
    value = float(record.get(selection.metric, float("nan")))
    if not np.isfinite(value):
      return (1, 0.0, record["seed"])
    return (0, -value if selection.higher_is_better else value, record["seed"])

  best = min(records, key=rank)["seed"]
  chosen = {"selected_seed": best, "metric": selection.metric, "higher_is_better": selection.higher_is_better,
            "seeds": records}
  os.makedirs(stage_dir, exist_ok=True)
  fileio.atomic_write_json(rundir.selection_path(stage_dir), chosen)
  if curves:
    history_lib.overlay_curves({f"seed {s}" + (" (selected)" if s == best else ""): h for s, h in curves.items()},
                               selection.metric, rundir.seeds_figure(stage_dir, selection.metric),
                               title=f"{title} validation {selection.name} per seed, {config.name}")
  summary = ", ".join(f"seed {r['seed']}: {r.get(selection.metric, float('nan')):.3f}" for r in records)
  print(f"[pretrain] {title} final validation {selection.name}: {summary}; selected seed {best} "
        f"({rundir.selection_path(stage_dir)})", flush=True)
  return chosen


def run(config, workdir: str, make_validation: Optional[MakeValidation] = None) -> None:
  """The pretrain stage: trains the model of the run's encoder on the dataset of `config` (roboshape.data) to
  pretrain.train.steps, once per seed of pretrain.train_seeds (`train_and_select`), validated by
  `make_validation` (roboshape/stages.py passes the encoder's evaluator)."""
  train_and_select(config, workdir, lambda seed_config: data_source(seed_config, workdir), make_validation)
