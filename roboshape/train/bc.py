"""The "train_policy" stage: behaviour cloning of the transformer policy on cached frozen-encoder features.

  python launch.py --config=configs/pick_savi.py:tiny          # the whole chain; this stage after "cache"
  policy = roboshape.load_policy(workdir)      # load_policy below: a roboshape.models.policy.Policy (reset, act)

Samples. A sample is a window of H consecutive cached frames of one training episode, frames s .. s+H-1 with
s uniform over the episode's windows; the [ACT] token of window position p predicts action s+p, and every
position is a target (NLL averaged over them). Episode starts need no padding:
the trunk is causal over time, so positions 0..p of the window starting at frame 0 are exactly what control sees
at step p < H (it reads out at the newest frame of a growing history; see roboshape/models/policy.py). Episodes
shorter than H repeat their last frame and mask the targets past their end. Only successful demos are used.

Outputs in <workdir>/policy/: checkpoints/ (orbax: the train state {params, opt_state, step}, and the params
again on their own, which `load_params` restores without building an optimizer), tb/ (TensorBoard: train NLL,
learning rate, gradient norm, validation NLL and action MSE), norm_stats.json (the action normalisation:
a = scale * a_norm + offset; identity when the demos' actions already lie in [-1, 1]), summary.json (the final
validation figures), val_metrics.json / .png (every validation result, across resumes, and its curves). The stage
skips when the last checkpoint is at config's steps. Every batch is split over the local devices, parameters
replicated (roboshape/train/sharding.py, as SAVi's pretraining does; launch.py makes each CPU core a device).
A non-finite loss or gradient norm stops training at once (roboshape/train/divergence.py, as pretraining does):
each step's metrics are checked before anything is logged or saved, and the parameters before every save, so no
checkpoint of non-finite parameters is written; the last finite one stays and the stage is not done.
"""
import functools
import json
import os
import time
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from roboshape import fileio
from roboshape import progress
from roboshape import ranges
from roboshape import rundir
from roboshape.checkpoint import Checkpointer
from roboshape.errors import UserError
from roboshape.models import heads
from roboshape.models import policy as policy_lib
from roboshape.train import cache
from roboshape.train import divergence
from roboshape.train import history as history_lib
from roboshape.train import scalars
from roboshape.train import sharding


# ----------------------------------------------------------------------------------------------------------------
# Action normalisation.


# The ranges of the policy section's training fields (the trunk's own: roboshape/models/policy.py RANGES).
RANGES = (
    ranges.Int("policy.train.steps", 1, "gradient steps; evaluate needs the checkpoint they leave"),
    ranges.Int("policy.train.batch_size", 1, "windows per gradient step"),
    ranges.Int("policy.train.warmup_steps", 0, "steps of linear learning-rate warmup"),
    ranges.Int("policy.train.log_every", 1, "steps between TensorBoard logs"),
    ranges.Int("policy.train.eval_every", 1, "steps between validations"),
    ranges.Int("policy.train.checkpoint_every", 1, "steps between checkpoints"),
    ranges.Int("policy.train.val_batch_size", 1, "windows per validation batch"),
    ranges.Int("policy.train.max_val_samples", 1, "action targets scored per validation"),
    ranges.Number("policy.train.learning_rate", 0.0, "the peak learning rate", low_ok=False),
    ranges.Number("policy.train.weight_decay", 0.0, "AdamW's weight decay"),
    ranges.Number("policy.train.grad_clip", 0.0, "the global gradient-norm clip", low_ok=False),
    ranges.Number("policy.train.change_weight", 0.0, "the loss weight of a step where the gripper command changes",
                  low_ok=False),
    ranges.Ints("policy.train_seeds", 0, "one policy per training seed; (): one policy trained with config.seed",
                empty_ok=True, distinct=True),
)


def check_config(config) -> None:
  """Raises UserError for the first bad field of the policy's training: RANGES, then the feature cache's dtype
  (roboshape/train/cache.py); roboshape/config_check.py runs it before any stage."""
  ranges.check(config, RANGES)
  cache.check_config(config)


def norm_stats(actions: np.ndarray) -> Dict[str, list]:
  """Statistics of demo actions [F, A]: identity when all lie in [-1, 1], else min/max mapped onto [-1, 1]."""
  lo, hi = actions.min(axis=0), actions.max(axis=0)
  if lo.min() >= -1.0 and hi.max() <= 1.0:
    scale, offset = np.ones_like(lo), np.zeros_like(lo)
  else:
    offset = (hi + lo) / 2
    scale = np.where(hi - lo > 1e-8, (hi - lo) / 2, 1.0)
  return dict(scale=scale.tolist(), offset=offset.tolist(), min=lo.tolist(), max=hi.tolist(),
              mean=actions.mean(axis=0).tolist(), std=actions.std(axis=0).tolist())


# ----------------------------------------------------------------------------------------------------------------
# Windows of cached features.


def present_slots(*features: np.ndarray) -> np.ndarray:
  """Indices of the token slots (axis 1 of each features [F, N, D]) that hold a non-zero token in some frame.

  A slot that is all zero in every frame is padding everywhere (an `objects` id that never appears, e.g. a
  distractor beyond the level's count): the trunk masks padding out (roboshape/models/policy.py), so training on
  the other slots alone gives the same outputs at a cost about proportional to the slots kept. At control time the
  policy reads every slot, padding included, with the same outputs."""
  kept = np.zeros(features[0].shape[1], bool)
  for part in features:
    for start in range(0, len(part), 65536):             # in chunks: a [F, N, D] boolean at once is large
      kept |= np.any(part[start:start + 65536] != 0, axis=(0, 2))
  return np.flatnonzero(kept) if kept.any() else np.arange(len(kept))


def gripper_changes(actions: np.ndarray, offsets: np.ndarray) -> np.ndarray:
  """Frame indices [K] whose gripper command (sign of the last action entry) differs from the previous frame's in
  the same episode; `offsets` [E + 1] are the episodes' first frames. An episode's first frame is never one."""
  opened = actions[:, -1] > 0
  changed = np.flatnonzero(opened[1:] != opened[:-1]) + 1
  return changed[~np.isin(changed, offsets)]


class Windows:
  """The windows of one split's cached episodes, gathered into batches.

  Args:
    data: `cache.load_split` output (features [F, N, D], action [F, A], offsets [E + 1], success [E]).
    history: H.
    normalise: (scale, offset) arrays [A]; targets are (action - offset) / scale.
    successful_only: drop failed episodes.
    change_weight: the loss weight of a target whose gripper command (the action's last entry, open > 0 > closed)
      differs from the episode's previous one: the grasp and the release, a few steps of each demo, which a
      mixture fitted to every step equally can leave to a light mode. 1: every target weighs the same.
  """

  def __init__(self, data: dict, history: int, normalise, successful_only: bool = True, change_weight: float = 1.0):
    self.features, self.history = data["features"], history
    scale, offset = (np.asarray(v, np.float32) for v in normalise)
    self.action = (data["action"] - offset) / scale
    self.weight = np.ones(len(data["action"]), np.float32)
    if change_weight != 1.0:
      self.weight[gripper_changes(data["action"], data["offsets"])] = change_weight
    keep = np.flatnonzero(data["success"]) if successful_only else np.arange(len(data["success"]))
    if not len(keep):
      raise UserError("no successful episodes in the cached dataset: nothing to imitate.")
    starts, frames = data["offsets"][keep], np.diff(data["offsets"])[keep]
    self.num_episodes, self.num_actions = len(keep), int((frames - 1).sum())
    per_episode = np.maximum(frames - 1 - history, 0) + 1            # windows per episode (T - H + 1, at least 1)
    self.episode_start = np.repeat(starts, per_episode)
    self.episode_frames = np.repeat(frames, per_episode)
    self.window_start = np.concatenate([np.arange(n) for n in per_episode])

  def __len__(self) -> int:
    return len(self.window_start)

  def gather(self, rows: np.ndarray) -> dict:
    """Windows `rows` -> tokens [B, H, N, D], action [B, H, A], mask float32 [B, H], weight float32 [B, H].

    Position p's target is the action taken at its frame; a frame repeated past an episode's last action (the
    padding of a short episode) is masked. `weight` is the mask times each target's loss weight (change_weight)."""
    start, frames, s = self.episode_start[rows], self.episode_frames[rows], self.window_start[rows]
    local = s[:, None] + np.arange(self.history)[None]                                 # [B, H]
    frame_idx = start[:, None] + np.minimum(local, frames[:, None] - 1)
    mask = (local < (frames - 1)[:, None]).astype(np.float32)
    return dict(tokens=np.asarray(self.features[frame_idx], np.float32), action=self.action[frame_idx],
                mask=mask, weight=mask * self.weight[frame_idx])

  def sample(self, batch_size: int, seed: int, step: int) -> dict:
    """A training batch, the same for the same (seed, step), so a resumed run sees the same data."""
    rng = np.random.default_rng([seed, step])
    return self.gather(rng.integers(0, len(self), size=batch_size))

  def eval_batches(self, batch_size: int, max_samples: int):
    """Every window (evenly thinned to at most `max_samples`) in fixed-size batches; padding rows have mask 0."""
    rows = np.arange(len(self))
    if len(rows) > max_samples:
      rows = rows[np.linspace(0, len(rows) - 1, max_samples).astype(int)]
    for i in range(0, len(rows), batch_size):
      part = rows[i:i + batch_size]
      batch = self.gather(np.concatenate([part, np.repeat(part[-1:], batch_size - len(part))]))
      batch["mask"][len(part):] = 0.0
      yield batch


# ----------------------------------------------------------------------------------------------------------------
# Pure training functions.


def make_schedule(train_config) -> optax.Schedule:
  """Linear warmup from 0 to the learning rate, then cosine decay to a tenth of it at the last step."""
  t = train_config
  return optax.warmup_cosine_decay_schedule(0.0, t.learning_rate, max(t.warmup_steps, 1),
                                            max(t.steps, t.warmup_steps + 1), end_value=0.1 * t.learning_rate)


def make_optimizer(train_config) -> optax.GradientTransformation:
  """AdamW on the warmup + cosine schedule, after global-norm gradient clipping."""
  return optax.chain(optax.clip_by_global_norm(train_config.grad_clip),
                     optax.adamw(make_schedule(train_config), weight_decay=train_config.weight_decay))


def _read_out_frames(batch_size: int, history: int) -> jax.Array:
  return jnp.broadcast_to(jnp.arange(history), (batch_size, history))


def losses(net, params, batch, rng=None, train: bool = False):
  """NLL [B, H] and squared error of the mixture mean [B, H, A], in normalised action units."""
  tokens = batch["tokens"]
  gmm = net.apply(params, tokens, _read_out_frames(tokens.shape[0], tokens.shape[1]), train=train,
                  rngs={"dropout": rng} if train else None)
  nll = -heads.gmm_log_prob(gmm, batch["action"])
  sq = (heads.gmm_mean(gmm) - batch["action"]) ** 2
  return nll, sq


def init_params(net, tokens_shape, seed: int):
  """The policy's variables for tokens of shape [B, H, N, D] (the train state's "params")."""
  return net.init(jax.random.PRNGKey(seed), jnp.zeros(tokens_shape, jnp.float32),
                  _read_out_frames(tokens_shape[0], tokens_shape[1]))


def init_state(net, optimizer, tokens_shape, seed: int):
  """The train state {params, opt_state, step} for tokens of shape [B, H, N, D] (built by one compiled call)."""
  def build():
    params = init_params(net, tokens_shape, seed)
    return dict(params=params, opt_state=optimizer.init(params), step=jnp.zeros((), jnp.int32))
  return jax.jit(build)()


def make_train_step(net, optimizer):
  """The jitted pure step `(state, batch, rng) -> (state, metrics)`; dropout uses fold_in(rng, state's step)."""
  def loss_fn(params, batch, rng):
    nll, sq = losses(net, params, batch, rng, train=True)
    denom = jnp.maximum(batch["mask"].sum(), 1.0)
    weight = batch.get("weight", batch["mask"])         # Windows.gather's per-target loss weight; the mask's mean at 1
    loss = jnp.sum(nll * weight) / jnp.maximum(weight.sum(), 1e-6)
    return loss, jnp.sum(sq.sum(-1) * batch["mask"]) / denom
  @jax.jit
  def step(state, batch, rng):
    rng = jax.random.fold_in(rng, state["step"])
    (loss, sq), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"], batch, rng)
    updates, opt_state = optimizer.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    metrics = dict(nll=loss, action_mse=sq / batch["action"].shape[-1], grad_norm=optax.tree.norm(grads))
    return dict(params=params, opt_state=opt_state, step=state["step"] + 1), metrics
  return step


def make_eval_step(net):
  """The jitted `(params, batch) -> (sum NLL, sum squared error per action dim [A], count)` over masked targets."""
  @jax.jit
  def step(params, batch):
    nll, sq = losses(net, params, batch)
    return (jnp.sum(nll * batch["mask"]), jnp.sum(sq * batch["mask"][..., None], axis=(0, 1)),
            batch["mask"].sum())
  return step


def evaluate(eval_step, params, windows: Windows, batch_size: int, max_samples: int, scale) -> dict:
  """Validation NLL (of normalised actions) and action MSE of the mixture mean (env units, mean over dims)."""
  nll, sq, n = 0.0, 0.0, 0.0
  for batch in windows.eval_batches(batch_size, max_samples):
    a, b, c = eval_step(params, batch)
    nll, sq, n = nll + float(a), sq + np.asarray(b, np.float64), n + float(c)
  mse = float(np.mean(sq * np.square(np.asarray(scale, np.float64)))) / max(n, 1.0)
  return dict(nll=nll / max(n, 1.0), action_mse=mse, targets=n)


# ----------------------------------------------------------------------------------------------------------------
# The stage.


ENCODER_FILE = "encoder.json"        # <policy_dir>/encoder.json: the encoder the policy was trained on
NORM_STATS_FILE = "norm_stats.json"  # <policy_dir>/norm_stats.json: the action normalisation
SUMMARY_FILE = "summary.json"        # <policy_dir>/summary.json: the final validation figures


def _portable(identity: str, workdir: str) -> str:
  """An encoder identity with the workdir's absolute path as "<workdir>", so a moved workdir keeps its identities."""
  return identity.replace(os.path.abspath(workdir), "<workdir>")


def check_encoder(workdir: str, identity: str, train_seed=None) -> None:
  """Raises a one-line UserError when the policy in `workdir` was trained on another encoder than `identity`.

  <workdir>/policy/encoder.json records the encoder a policy was trained on (written by `train`); a run trained
  before it existed is not checked.
  """
  out = rundir.policy_dir(workdir, train_seed)
  path = os.path.join(out, ENCODER_FILE)
  if not os.path.exists(path):
    return
  with open(path) as f:
    trained_on = json.load(f)["identity"]
  now = _portable(identity, workdir)
  if trained_on != now:
    raise UserError(f"the policy in {out} was trained on encoder {trained_on}, the workdir's encoder is now {now}: "
                    "its actions would be meaningless, and the policy is left as it is. To train one on the current "
                    f"encoder, rename {out} (e.g. to {out}.old, which keeps it) and run the train_policy stage "
                    "again.")


def _record_encoder(config, workdir: str, feature_path: str, resuming: bool, train_seed=None) -> None:
  """Checks the cached features' encoder against the one the policy was trained on, and records it when new."""
  manifest = cache.read_manifest(feature_path)
  if manifest is None:
    raise UserError(f"no complete feature cache in {feature_path} (no manifest.json): run the cache stage first.")
  path = os.path.join(rundir.policy_dir(workdir, train_seed), ENCODER_FILE)
  if resuming:
    check_encoder(workdir, manifest["encoder_identity"], train_seed)
    if os.path.exists(path):
      return
  fileio.atomic_write_json(path, dict(encoder=manifest.get("encoder", config.encoder),
                                      identity=_portable(manifest["encoder_identity"], workdir),
                                      features=os.path.basename(os.path.normpath(feature_path))))


def _trained(ckpt: Checkpointer, steps: int, summary_path: str) -> bool:
  """Whether training is done: a summary and a last checkpoint at `steps` or later that restores."""
  latest = ckpt.latest_step()
  return latest is not None and latest >= steps and os.path.exists(summary_path) and ckpt.restores(latest)


def train(config, workdir: str, feature_path: str, train_seed=None) -> dict:
  """Trains (or resumes) the policy on the features cached in `feature_path`; returns the final validation metrics.

  Resumes from the newest checkpoint that restores (a damaged newer one is set aside with a warning). A policy
  whose checkpoints were trained on another encoder than the features' is refused (`check_encoder`).
  """
  out = rundir.policy_dir(workdir, train_seed)
  os.makedirs(out, exist_ok=True)
  with Checkpointer(rundir.checkpoints(out), keep=2) as ckpt:
    _record_encoder(config, workdir, feature_path, resuming=ckpt.latest_step() is not None, train_seed=train_seed)
    summary_path = os.path.join(out, SUMMARY_FILE)
    if _trained(ckpt, config.policy.train.steps, summary_path):
      print(f"[train_policy] already trained to step {ckpt.latest_step()}: skipping", flush=True)
      with open(summary_path) as f:
        return json.load(f)
    summary = _fit(config, out, feature_path, ckpt, config.seed if train_seed is None else int(train_seed))
  fileio.atomic_write_json(summary_path, summary)
  return summary


def _keep_interrupted(ckpt: Checkpointer, state, start: int) -> None:
  """After an interrupt (Ctrl-C, a grid stopped at the end of a session), a checkpoint of the steps done since the
  newest one, so the resume repeats none of them: batches and dropout are drawn from the step, so a run resumed
  from any step ends where an uninterrupted one does. The validation history's train_seconds then leaves out the
  interrupted attempt's steps after its last validation; the stage log (stages.json) counts every attempt."""
  ckpt.wait()
  step = int(state["step"])
  if step > start and step != ckpt.latest_step() and divergence.finite(state["params"]):
    ckpt.save(step, state)
    ckpt.wait()
    tqdm.write(f"[train_policy] interrupted: saved step {step}")


def _save_finite(ckpt: Checkpointer, step: int, state, learning_rate: float) -> None:
  """Saves `state` as checkpoint `step` unless its parameters are not finite (a Diverged error then, the last
  finite checkpoint kept): no non-finite checkpoint is ever written, whatever the metrics said."""
  divergence.check_params(state["params"], step, ckpt, stage="train_policy", what="the policy's",
                          fields={"policy.train.learning_rate": learning_rate})
  ckpt.save(step, state)


def _fit(config, out: str, feature_path: str, ckpt: Checkpointer, seed: int) -> dict:
  """The training loop of `train`, from the newest checkpoint in `ckpt` that restores; returns the summary.
  `seed` draws the initial params, the dropout masks and the batches."""
  pc, tc = config.policy, config.policy.train
  train_data, val_data = cache.load_split(feature_path, "train"), cache.load_split(feature_path, "val")
  stats_path = os.path.join(out, NORM_STATS_FILE)
  if os.path.exists(stats_path):
    with open(stats_path) as f:
      stats = json.load(f)
  else:
    valid_rows = np.concatenate([np.arange(a, b - 1) for a, b in zip(train_data["offsets"][:-1],
                                                                      train_data["offsets"][1:])])
    stats = norm_stats(train_data["action"][valid_rows])
    fileio.atomic_write_json(stats_path, stats)
  normalise = (stats["scale"], stats["offset"])
  slots, all_slots = present_slots(train_data["features"], val_data["features"]), train_data["features"].shape[1]
  for data in (train_data, val_data):
    data["features"] = data["features"][:, slots]
  train_w = Windows(train_data, pc.history, normalise, change_weight=tc.change_weight)
  val_w = Windows(val_data, pc.history, normalise)
  print(f"[train_policy] {train_w.num_episodes} train episodes ({len(train_w)} windows), "
        f"{val_w.num_episodes} val episodes; tokens {train_data['features'].shape[1:]} "
        f"({all_slots - len(slots)} of {all_slots} slots dropped: padding in every frame)", flush=True)

  net = policy_lib.net_from_config(pc)
  optimizer, schedule = make_optimizer(tc), make_schedule(tc)
  n, d = train_data["features"].shape[1:]
  dp = sharding.DataParallel(tc.batch_size, tc.val_batch_size)    # every batch split over the local devices
  state, _ = ckpt.resume(init_state(net, optimizer, (tc.batch_size, pc.history, n, d), seed))
  state = jax.device_put(state, dp.replicated)
  train_step, device_eval_step = make_train_step(net, optimizer), make_eval_step(net)

  def eval_step(params, batch):
    return device_eval_step(params, dp.put_batch(batch))
  start = int(state["step"])
  base_rng = jax.random.PRNGKey(seed)
  writer = scalars.Scalars(os.path.join(out, "tb"))
  metrics = None
  val = {}
  seconds_before, run_start = history_lib.seconds_at(out, "val_metrics", start), time.perf_counter()
  def stop_if_diverged(step_metrics, step: int) -> None:
    values = jax.device_get(step_metrics)
    divergence.check({"loss": values["nll"], "gradient norm": values["grad_norm"]}, step, ckpt,
                     stage="train_policy", what="the policy's", fields={"policy.train.learning_rate": tc.learning_rate})

  try:
    for step in progress.bar(range(start, tc.steps), desc="train_policy", initial=start, total=tc.steps):
      batch = dp.put_batch(train_w.sample(tc.batch_size, seed, step))
      previous = metrics
      state, metrics = train_step(state, batch, base_rng)
      if previous is not None:      # at most one step in flight: the bar's rate is the steps' rate, not dispatch's
        stop_if_diverged(previous, step)
      done = step + 1
      if (done % tc.log_every == 0 or done % tc.eval_every == 0 or done % tc.checkpoint_every == 0
          or done == tc.steps):     # this step's metrics are checked before anything is logged or saved
        stop_if_diverged(metrics, done)
      if done % tc.log_every == 0 or done == tc.steps:
        writer.write(done, {**{f"train/{k}": float(v) for k, v in metrics.items()},
                            "train/learning_rate": float(schedule(step))})
      if done % tc.eval_every == 0 or done == tc.steps:
        val = evaluate(eval_step, state["params"], val_w, tc.val_batch_size, tc.max_val_samples, normalise[0])
        writer.write(done, {"val/nll": val["nll"], "val/action_mse": val["action_mse"]})
        history_lib.record(out, "val_metrics", done, dict(val, train_nll=float(metrics["nll"])),
                           seconds_before + time.perf_counter() - run_start, keys=("train_nll", "nll", "action_mse"),
                           title=f"policy validation, {config.name}")
        tqdm.write(f"[train_policy] step {done}: train nll {float(metrics['nll']):.3f}, "
                   f"val nll {val['nll']:.3f}, val action mse {val['action_mse']:.5f}")
      if done % tc.checkpoint_every == 0 or done == tc.steps:
        _save_finite(ckpt, done, state, tc.learning_rate)
  except KeyboardInterrupt:
    _keep_interrupted(ckpt, state, start)
    raise
  finally:
    writer.close()      # what TensorBoard got so far, also after an interrupt
  ckpt.wait()
  if not val:
    val = evaluate(eval_step, state["params"], val_w, tc.val_batch_size, tc.max_val_samples, normalise[0])
  return dict(step=int(state["step"]), val_nll=val["nll"], val_action_mse=val["action_mse"],
              train_episodes=train_w.num_episodes, val_episodes=val_w.num_episodes,
              features=os.path.abspath(feature_path))


def run(config, workdir: str) -> None:
  """The train_policy stage: caches the features if the cache stage has not, then trains one policy per training
  seed (`rundir.train_seeds`: config.policy.train_seeds, or one policy with config.seed).

  A policy trained on another encoder than the workdir's now (e.g. SAVi pretrained further since) is refused.
  """
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  encoder = encoders.build_encoder(config, workdir)
  todo = []
  for seed in rundir.train_seeds(config):
    check_encoder(workdir, encoder.identity, seed)
    out = rundir.policy_dir(workdir, seed)
    if os.path.isdir(rundir.checkpoints(out)):
      with Checkpointer(rundir.checkpoints(out)) as ckpt:
        if _trained(ckpt, config.policy.train.steps, os.path.join(out, SUMMARY_FILE)):
          print(f"[train_policy] {_seed_name(seed)}already trained to step {ckpt.latest_step()}: skipping",
                flush=True)
          continue
    todo.append(seed)
  if todo:
    feature_path = cache.build(config, workdir, encoder)
    for seed in todo:
      print(f"[train_policy] {_seed_name(seed)}-> {rundir.policy_dir(workdir, seed)}", flush=True)
      train(config, workdir, feature_path, seed)


def _seed_name(seed) -> str:
  return "" if seed is None else f"training seed {seed}: "


# ----------------------------------------------------------------------------------------------------------------
# Loading for closed-loop control.


def load_params(config, workdir: str, num_tokens: int, token_dim: int, step: Optional[int] = None,
                train_seed=None):
  """(net, the trained trunk+head params) from <workdir>/policy/checkpoints (latest step by default): the params
  alone, restored without building an optimizer. A run trained with action chunks is refused in one line
  (rundir.check_no_chunks)."""
  rundir.check_no_chunks(config, workdir)
  pc = config.policy
  net = policy_lib.net_from_config(pc)
  like = jax.eval_shape(functools.partial(init_params, net, (1, pc.history, num_tokens, token_dim), config.seed))
  ckpt_dir = rundir.checkpoints(rundir.policy_dir(workdir, train_seed))
  if not os.path.isdir(ckpt_dir):
    raise UserError(f"no policy checkpoint in {ckpt_dir}: run the train_policy stage first.")
  with Checkpointer(ckpt_dir) as ckpt:
    if ckpt.latest_step() is None:
      raise UserError(f"no policy checkpoint in {ckpt_dir}: run the train_policy stage first.")
    params = ckpt.restore_params(like, step)
  # on one device, as the controller's carry (where the checkpoint restores a target without shardings anyway)
  return net, jax.device_put(params, jax.devices()[0])


def load_policy(workdir: str, history: Optional[int] = None, action: Optional[str] = None,
                step: Optional[int] = None, seed: int = 0, train_seed=None) -> policy_lib.Policy:
  """The closed-loop `Policy` of the run in `workdir` (roboshape/models/policy.py: reset, act, act_batch).

  Args:
    workdir: a run's workdir (config.json, policy/checkpoints, policy/norm_stats.json, the encoder's files).
    history: frames seen at control time (default config.policy.eval.history, 0 meaning the training history).
    action: "mean" or "sample" (default config.policy.eval.action).
    step: the checkpoint step (default: the latest).
    seed: the sampling seed (action="sample").
    train_seed: which policy of a run with `policy.train_seeds` (default: its first; without: the one in policy/).
  """
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  config = rundir.load_config(workdir)
  if train_seed is None:
    train_seed = rundir.train_seeds(config)[0]
  encoder = encoders.build_encoder(config, workdir)
  check_encoder(workdir, encoder.identity, train_seed)
  net, params = load_params(config, workdir, encoder.num_tokens, encoder.token_dim, step, train_seed)
  with open(os.path.join(rundir.policy_dir(workdir, train_seed), NORM_STATS_FILE)) as f:
    stats = json.load(f)
  ev = config.policy.eval
  spec = policy_lib.ControlSpec(history=history or ev.history or config.policy.history,
                                action=action or ev.action, noise=ev.noise)
  return policy_lib.Policy(net, params, encoder, spec, stats["scale"], stats["offset"], seed=seed)


# ----------------------------------------------------------------------------------------------------------------
# A policy that cannot act.


def how_trained(workdir: str, train_seed=None) -> str:
  """"checkpoint step N in <dir>, trained with policy.train.learning_rate=..., ..." for the messages that blame a
  policy: its newest checkpoint and the optimisation settings its fingerprint.json records (the workdir's
  config.json for a policy trained before fingerprints were recorded)."""
  from roboshape.train import fingerprint  # pylint: disable=import-outside-toplevel
  config = rundir.load_config(workdir)
  fields, from_config = fingerprint.recorded(config, workdir, "train_policy")
  source = rundir.fingerprint_path(rundir.policy_dir(workdir))
  if fields is None or from_config:
    fields, source = fingerprint.fingerprint(config, "train_policy"), rundir.config_path(workdir)
  out = rundir.policy_dir(workdir, train_seed)
  steps = rundir.saved_steps(out)
  settings = ", ".join(f"{k}={fields[k]!r}" for k in (f"policy.train.{f}" for f in (
      "learning_rate", "grad_clip", "warmup_steps", "batch_size")) if k in fields)
  return (f"checkpoint step {steps[-1] if steps else '?'} in {rundir.checkpoints(out)}, trained with {settings} "
          f"({source})")


def _cannot_act(workdir: str, train_seed, what: str) -> UserError:
  return UserError(f"the policy in {rundir.policy_dir(workdir, train_seed)} cannot act: {what}. It is the policy's "
                   f"fault, not the simulator's: {how_trained(workdir, train_seed)}. Train it again with settings "
                   "that keep its loss finite (e.g. a lower --config.policy.train.learning_rate) with "
                   "--redo=train_policy, or in another --workdir.")


class ActingPolicy:
  """A loaded `Policy` whose actions are checked: `act_batch` and `act` raise a one-line UserError naming the
  policy's checkpoint and how it was trained when an action is NaN or inf (which the simulator could not take);
  everything else is the policy's own."""

  def __init__(self, policy: policy_lib.Policy, workdir: str, train_seed=None):
    self._policy, self._workdir, self._train_seed = policy, workdir, train_seed

  def __getattr__(self, name):
    return getattr(self._policy, name)

  def act_batch(self, frames) -> np.ndarray:
    actions = self._policy.act_batch(frames)
    if not np.all(np.isfinite(actions)):
      rows = np.flatnonzero(~np.all(np.isfinite(actions), axis=-1))
      raise _cannot_act(self._workdir, self._train_seed,
                        f"its actions are not finite (NaN or inf) for env(s) {rows.tolist()} of the batch at "
                        f"control step {int(np.max(np.asarray(self._policy.carry.count)))}")
    return actions

  def act(self, frame) -> np.ndarray:
    return self.act_batch(jax.tree.map(lambda x: np.asarray(x)[None], frame))[0]


def acting_policy(workdir: str, train_seed=None) -> ActingPolicy:
  """`load_policy(workdir, train_seed=...)` for closed-loop evaluation: a one-line UserError naming the checkpoint
  and how it was trained when its parameters are not all finite (a policy trained before training stopped at a
  diverging loss), and its actions checked as it acts (`ActingPolicy`)."""
  policy = load_policy(workdir, train_seed=train_seed)
  if not divergence.finite(policy.params):
    raise _cannot_act(workdir, train_seed, "its parameters are not finite (NaN or inf)")
  return ActingPolicy(policy, workdir, train_seed)
