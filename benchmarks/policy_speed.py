"""Behaviour-cloning and control speed of the transformer policy over SAVi, all measured in one run.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/policy_speed.py [--variant paper] [--episodes 8] [--batch 64]

Prints:
  1. the time to encode a synthetic dataset (episodes of 60 steps at 64x64) once with SAVi (the cache stage);
  2. one BC epoch (every window once) on the cached features, and one BC epoch that re-encodes each sample's
     frames with SAVi inside the train step instead, in two ways: the window's H frames alone (the cheapest, but
     SAVi then starts from its initial slots at the window's first frame, so its slots differ from the cache's),
     and the sample's episode from its first frame up to the window (the same slots as the cache, which runs
     SAVi recurrently over whole episodes). Bar: cached >= 5x faster;
  3. `policy.act` latency (batch 1, SAVi step + trunk + head) next to one rendered env step of the simulator
     (roboshape.sim.SimPool, one worker, 64x64) measured in the same run. Bar: act() <= 0.5 x env step;
  4. the FLOPs of one act() (XLA cost analysis of the step as written: flops.step_flops) against the machine's
     dense-matmul FLOP/s.
SAVi and the policy have random weights of the variant's architecture: speed does not depend on the weights.
"""
import argparse
import functools
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # pylint: disable=wrong-import-position
import jax.numpy as jnp  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position

import flops  # pylint: disable=wrong-import-position  (benchmarks/flops.py)
from configs import common  # pylint: disable=wrong-import-position
from roboshape.models import policy as policy_lib  # pylint: disable=wrong-import-position
from roboshape.models.encoder import FrozenEncoder  # pylint: disable=wrong-import-position
from roboshape.train import bc  # pylint: disable=wrong-import-position
from roboshape.train import cache  # pylint: disable=wrong-import-position
from roboshape.models import savi  # pylint: disable=wrong-import-position
from roboshape.train import pretrain  # pylint: disable=wrong-import-position


def random_savi(config) -> FrozenEncoder:
  comp = pretrain.compiled(config)
  r = config.env.resolution
  params = comp.init_state(jax.random.key(0), (1, config.pretrain.train.clip_length, r, r, 3))["params"]
  init = savi.initial_slots(comp.model, params, 1)[0]
  return FrozenEncoder(
      name="savi", params=params, step=functools.partial(savi.frozen_step, comp.model),
      init_state=lambda b: jnp.broadcast_to(init, (b, *init.shape)), num_tokens=comp.model.num_slots,
      token_dim=comp.model.slot_size, identity="savi:random")


def synthetic_episodes(n: int, steps: int, res: int):
  rng = np.random.default_rng(0)
  return [dict(seed=i, success=True, image=rng.integers(0, 256, (steps + 1, res, res, 3), dtype=np.uint8),
               action=rng.uniform(-1, 1, (steps, 7)).astype(np.float32)) for i in range(n)]


def bc_epochs(config, encoder, episodes, feature_dir, batch_size, reencode_steps):
  """Seconds of one BC epoch: on cached features, re-encoding each window, re-encoding each episode prefix.

  The cached epoch is timed in full; the re-encoding epochs are timed over their first `reencode_steps` steps and
  scaled to the epoch's steps (every step of an epoch has the same shapes, so the same cost).
  """
  pc = config.policy
  data = cache.load_split(feature_dir, "train")
  windows = bc.Windows(data, pc.history, ([1.0] * 7, [0.0] * 7))
  frames = np.concatenate([e["image"] for e in episodes], axis=0)           # [F, H, W, 3], same rows as features
  net, optimizer = policy_lib.net_from_config(pc), bc.make_optimizer(pc.train)
  n, d = data["features"].shape[1:]
  state = bc.init_state(net, optimizer, (batch_size, pc.history, n, d), 0)
  train_step = bc.make_train_step(net, optimizer)
  rng = jax.random.PRNGKey(0)
  order = np.random.default_rng(0).permutation(len(windows))
  steps = -(-len(windows) // batch_size)
  batches = [np.resize(order[i * batch_size:(i + 1) * batch_size], batch_size) for i in range(steps)]
  longest = int(windows.episode_frames.max())

  @jax.jit
  def window_step(state, video, action, mask, rng):
    tokens = encoder.encode_batch(video)                                        # [B, H, N, D]
    return train_step(state, dict(tokens=tokens, action=action, mask=mask), rng)

  @jax.jit
  def prefix_step(state, video, start, action, mask, rng):
    tokens = encoder.encode_batch(video)                                        # [B, L, N, D] from frame 0
    idx = start[:, None] + jnp.arange(pc.history)[None]
    tokens = jnp.take_along_axis(tokens, idx[:, :, None, None], axis=1)        # the window's H frames
    return train_step(state, dict(tokens=tokens, action=action, mask=mask), rng)

  def window_video(rows):
    start, count, s = windows.episode_start[rows], windows.episode_frames[rows], windows.window_start[rows]
    return frames[start[:, None] + np.minimum(s[:, None] + np.arange(pc.history)[None], count[:, None] - 1)]

  def prefix_video(rows):
    """Each sample's episode from its first frame to the window's end, padded to the longest episode."""
    start, count = windows.episode_start[rows], windows.episode_frames[rows]
    return frames[start[:, None] + np.minimum(np.arange(longest)[None], count[:, None] - 1)]

  def run(kind, rows_list):
    st, m = state, None
    for rows in rows_list:
      b = windows.gather(rows)
      if kind == "cached":
        st, m = train_step(st, b, rng)
      elif kind == "window":
        st, m = window_step(st, window_video(rows), b["action"], b["mask"], rng)
      else:
        s = np.minimum(windows.window_start[rows][:, None] + np.arange(pc.history)[None],
                       windows.episode_frames[rows][:, None] - 1)[:, 0]
        st, m = prefix_step(st, prefix_video(rows), s, b["action"], b["mask"], rng)
    jax.block_until_ready(m)

  out = {}
  for kind, count in (("cached", steps), ("window", reencode_steps), ("prefix", reencode_steps)):
    run(kind, batches[:1])                                                      # compile, not timed
    chosen = batches[:count]
    start = time.perf_counter()
    run(kind, chosen)
    out[kind] = (time.perf_counter() - start) / len(chosen) * steps
  return out, steps


def act_latency(config, encoder, reps: int):
  pc = config.policy
  net = policy_lib.net_from_config(pc)
  state = bc.init_state(net, bc.make_optimizer(pc.train), (1, pc.history, encoder.num_tokens, encoder.token_dim), 0)
  policy = policy_lib.Policy(net, state["params"], encoder, policy_lib.ControlSpec(history=pc.history),
                             np.ones(7, np.float32), np.zeros(7, np.float32))
  frames = np.random.default_rng(1).integers(0, 256, (reps + pc.history, 64, 64, 3), dtype=np.uint8)
  policy.reset()
  for f in frames[:pc.history]:       # warm up and fill the history (slides from here on)
    policy.act(f)
  times = []
  for f in frames[pc.history:]:
    start = time.perf_counter()
    policy.act(f)
    times.append(time.perf_counter() - start)
  step = policy._step  # pylint: disable=protected-access
  step_flops = flops.step_flops(step, policy.params, encoder.params, policy.carry, jnp.asarray(frames[:1]))
  return float(np.median(times)), step_flops, policy.num_traces


def env_step_time(task: str, reps: int):
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel
  rng = np.random.default_rng(0)
  times = []
  with SimPool(EnvSpec(task, resolution=64), num_workers=1) as pool:
    pool.reset([0])
    for i in range(reps + 3):
      action = rng.uniform(-0.3, 0.3, (1, 7)).astype(np.float32)
      start = time.perf_counter()
      out = pool.step(action)
      if i >= 3:
        times.append(time.perf_counter() - start)
      if out["done"][0]:
        pool.reset([i + 1])
  return float(np.median(times))


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--variant", default="paper", choices=common.VARIANTS)
  parser.add_argument("--episodes", type=int, default=8)
  parser.add_argument("--steps", type=int, default=60, help="actions per synthetic episode")
  parser.add_argument("--batch", type=int, default=64)
  parser.add_argument("--act_reps", type=int, default=30)
  parser.add_argument("--reencode_steps", type=int, default=2, help="timed steps of each re-encoding epoch")
  parser.add_argument("--task", default="pick")
  parser.add_argument("--skip_env", action="store_true", help="do not start the simulator")
  args = parser.parse_args()

  config = common.get_config(args.task, "savi", args.variant)
  config.env.resolution = 64
  pc = config.policy
  print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs; variant {args.variant}: "
        f"policy width {pc.width}, {pc.num_layers} layers, {pc.num_heads} heads, H={pc.history}; "
        f"SAVi {config.savi.num_slots} slots x {config.savi.slot_size}", flush=True)
  encoder = random_savi(config)
  episodes = synthetic_episodes(args.episodes, args.steps, 64)
  num_frames = sum(len(e["image"]) for e in episodes)
  with tempfile.TemporaryDirectory() as tmp:
    cache.encode_split(encoder, episodes[:cache.BATCH_EPISODES], os.path.join(tmp, "warmup"))   # compile
    start = time.perf_counter()
    cache.encode_split(encoder, episodes, os.path.join(tmp, "train"))
    encode_s = time.perf_counter() - start
    print(f"encode dataset once: {encode_s:.2f} s for {args.episodes} episodes / {num_frames} frames "
          f"({num_frames / encode_s:.1f} frames/s)", flush=True)
    epochs, steps = bc_epochs(config, encoder, episodes, tmp, args.batch, args.reencode_steps)
  cached_s = epochs["cached"]
  print(f"BC epoch ({steps} steps of batch {args.batch}, H={pc.history}); re-encoding epochs extrapolated from "
        f"{args.reencode_steps} timed steps:", flush=True)
  print(f"  cached features:                          {cached_s:8.2f} s", flush=True)
  for kind, what in (("window", "re-encoding each window's H frames"),
                     ("prefix", "re-encoding each episode up to the window")):
    ratio = epochs[kind] / cached_s
    print(f"  {what + ':':<41}{epochs[kind]:8.2f} s -> cached is {ratio:.1f}x faster "
          f"(bar >= 5x: {'PASS' if ratio >= 5 else 'FAIL'})", flush=True)
  act_s, act_flops, traces = act_latency(config, encoder, args.act_reps)
  peak = flops.matmul_flops_per_s()
  print(f"policy.act (batch 1, 64x64, SAVi + trunk): median {1e3 * act_s:.1f} ms over {args.act_reps} calls, "
        f"{traces} compilation(s); {act_flops / 1e9:.3f} GFLOP per act -> {act_flops / act_s / 1e9:.1f} GFLOP/s "
        f"vs dense matmul {peak / 1e9:.1f} GFLOP/s ({100 * act_flops / act_s / peak:.1f}% of it)", flush=True)
  if args.skip_env:
    return
  env_s = env_step_time(args.task, 30)
  print(f"env step ({args.task}, rendered 64x64, 1 worker): median {1e3 * env_s:.1f} ms -> act/env = "
        f"{act_s / env_s:.2f} (bar <= 0.5: {'PASS' if act_s / env_s <= 0.5 else 'FAIL'})", flush=True)


if __name__ == "__main__":
  main()
