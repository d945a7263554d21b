"""Behaviour-cloning train step at `:small`: steps/s and FLOP/s against a dense matmul, measured side by side.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/bc_speed.py [--variant small] [--tokens 9] [--rounds 5]
  JAX_PLATFORMS=cpu taskset -c 0 .venv/bin/python benchmarks/bc_speed.py    # one core: what one grid lane gets

One run times, alternately (round after round, the median of each kept, to damp a shared machine's noise):
  roboshape:   `bc.make_train_step` as the train_policy stage runs it on one device, the default on a CPU (batch,
               history and trunk from the variant's config; SAVi-like tokens: 9 per frame of width 128 at `:small`);
  N devices:   the same step with its batch split over N host devices, one per core of this process
               (roboshape/train/sharding.py; the script makes each core a device as launch.py does:
               roboshape/cli.py);
  no dropout:  the one-device step with the policy's dropout at 0 (what the dropout masks cost);
  frame pool:  the one-device step with policy.frame_pool (each frame's tokens pooled into one before the temporal
               transformer), its training samples (windows) per core-second beside the plain step's;
  matmul:      a dense float32 2048^3 matmul, and dense matmuls of the trunk's own shapes ([B*L, W] x [W, W] and
               [B*L, W] x [W, 4W], L = H x tokens + H read-out tokens), on the same device.
Prints each one's time, FLOPs (XLA cost analysis of the one-device step as written: flops.step_flops) and FLOP/s,
and the FLOP/s as a fraction of the 2048^3 matmul's. The bar, for the fastest step train_policy runs here (split over
the cores): >= 0.6 of the matmul, or >= 2x the one-device step's steps/s, both measured in this run (BASELINE_STEP_S,
the step the bar was set against on another 2-core machine, is printed for reference).
The trunk-shaped matmuls say what the step's dense layers could reach; the gap between them and the step
is the rest of the step (attention's small batched products, softmax, masks, layer norms, the optimizer).
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from roboshape import cli  # pylint: disable=wrong-import-position

CPUS = len(os.sched_getaffinity(0))
cli.host_device_per_core()   # before jax starts, as launch.py does

import jax  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position

import flops  # pylint: disable=wrong-import-position  (benchmarks/flops.py)
from configs import common  # pylint: disable=wrong-import-position
from roboshape.models import policy as policy_lib  # pylint: disable=wrong-import-position
from roboshape.train import bc  # pylint: disable=wrong-import-position
from roboshape.train import sharding  # pylint: disable=wrong-import-position

BASELINE_STEP_S = 0.50   # the :small step when the bar was set, on the first 2-core CPU (results/small/README.md)


def step_inputs(policy_config, tokens: int, token_dim: int, dp=None):
  """(jitted train step, initial state, batch, rng) for the policy the config section describes; with `dp` (a
  sharding.DataParallel) the batch is split over its devices and the state replicated, as train_policy does."""
  pc = policy_config
  b, h = pc.train.batch_size, pc.history
  net, optimizer = policy_lib.net_from_config(pc), bc.make_optimizer(pc.train)
  state = bc.init_state(net, optimizer, (b, h, tokens, token_dim), 0)
  rng = np.random.default_rng(0)
  batch = dict(tokens=rng.normal(size=(b, h, tokens, token_dim)).astype(np.float32),
               action=rng.uniform(-1, 1, (b, h, pc.action_dim)).astype(np.float32),
               mask=np.ones((b, h), np.float32))
  if dp is not None:
    state, batch = jax.device_put(state, dp.replicated), dp.put_batch(batch)
  return bc.make_train_step(net, optimizer), state, batch, jax.random.PRNGKey(0)


def compiled_step(policy_config, tokens: int, token_dim: int, dp=None):
  """(compiled step, its FLOPs, initial state, batch, rng): step_inputs' step compiled."""
  step, state, batch, key = step_inputs(policy_config, tokens, token_dim, dp)
  step_flops = flops.step_flops(step, state, batch, key)       # first: it fails in seconds, if at all
  return step.lower(state, batch, key).compile(), step_flops, state, batch, key


def time_steps(compiled, state, batch, key, steps: int) -> float:
  """Seconds per step over `steps` chained steps (each step's state feeds the next)."""
  start = time.perf_counter()
  metrics = None
  for _ in range(steps):
    state, metrics = compiled(state, batch, key)
  jax.block_until_ready(metrics)
  return (time.perf_counter() - start) / steps


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--variant", default="small", choices=common.VARIANTS)
  parser.add_argument("--tokens", type=int, default=9, help="tokens per frame (SAVi slots at :small)")
  parser.add_argument("--token_dim", type=int, default=128)
  parser.add_argument("--rounds", type=int, default=5)
  parser.add_argument("--steps", type=int, default=4, help="steps timed per round and variant")
  args = parser.parse_args()
  pc = common.get_config("push", "savi", args.variant).policy
  cpus = CPUS
  print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {cpus} of {os.cpu_count()} CPUs; variant "
        f"{args.variant}: batch {pc.train.batch_size}, H={pc.history}, {args.tokens} tokens x {args.token_dim}, "
        f"trunk width {pc.width}, {pc.num_layers} layers, {pc.num_heads} heads, dropout {pc.dropout}", flush=True)
  no_dropout = pc.copy_and_resolve_references()
  no_dropout.dropout = 0.0
  pooled = pc.copy_and_resolve_references()
  pooled.frame_pool = True
  steps = {"roboshape": compiled_step(pc, args.tokens, args.token_dim),
           "no dropout": compiled_step(no_dropout, args.tokens, args.token_dim),
           "frame pool": compiled_step(pooled, args.tokens, args.token_dim)}
  dp = sharding.DataParallel(pc.train.batch_size)
  if dp.num_devices > 1:
    steps[f"{dp.num_devices} devices"] = compiled_step(pc, args.tokens, args.token_dim, dp)
  rows = pc.train.batch_size * (pc.history * args.tokens + pc.history)
  shapes = {"2048^3": (2048, 2048, 2048), f"[{rows}, {pc.width}] x [{pc.width}, {pc.width}]": (rows, pc.width, pc.width),
            f"[{rows}, {pc.width}] x [{pc.width}, {4 * pc.width}]": (rows, pc.width, 4 * pc.width)}
  times = {name: [] for name in steps}
  rates = {name: [] for name in shapes}
  for _ in range(args.rounds):
    for name, (compiled, _, *inputs) in steps.items():
      times[name].append(time_steps(compiled, *inputs, args.steps))
    for name, shape in shapes.items():
      rates[name].append(flops.matmul_flops_per_s(reps=5, shape=shape))
  matmul = float(np.median(rates["2048^3"]))
  for name, values in rates.items():
    rate = float(np.median(values))
    print(f"matmul {name + ':':<28}{rate / 1e9:7.1f} GFLOP/s = {rate / matmul:.2f} of the 2048^3 matmul")
  work = steps["roboshape"][1]    # the step's FLOPs: the same work whether one device or several run it
  for name in steps:
    t = float(np.median(times[name]))
    step_flops = steps[name][1] if name in ("no dropout", "frame pool") else work
    print(f"{name + ' step:':<36}{1e3 * t:7.1f} ms ({1 / t:.2f} steps/s), {step_flops / 1e9:.1f} GFLOP -> "
          f"{step_flops / t / 1e9:.1f} GFLOP/s = {step_flops / t / matmul:.2f} of the 2048^3 matmul")
  one = float(np.median(times["roboshape"]))
  pool = float(np.median(times["frame pool"]))
  per_core_s = lambda t_step: pc.train.batch_size / t_step / cpus
  print(f"training samples per core-second: plain {per_core_s(one):.0f}, frame pool {per_core_s(pool):.0f} "
        f"({one / pool:.2f}x)")
  best = f"{dp.num_devices} devices" if dp.num_devices > 1 else "roboshape"
  t = float(np.median(times[best]))
  ratio, speedup = work / t / matmul, one / t
  print(f"bar (>= 0.6 of the matmul, or >= 2x the one-device step's steps/s, side by side): {best} step "
        f"{ratio:.2f} of the matmul, {speedup:.2f}x -> {'PASS' if ratio >= 0.6 or speedup >= 2 else 'FAIL'}")
  print(f"(the bar's reference, {BASELINE_STEP_S:.2f} s a step, was measured on another 2-core machine whose 2048^3 "
        f"matmul ran at 181-209 GFLOP/s; here {matmul / 1e9:.0f}: {BASELINE_STEP_S / t:.2f}x that step's steps/s)")

if __name__ == "__main__":
  main()
