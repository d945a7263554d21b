"""SAVi train-step throughput, and how much of the machine's dense-matmul speed the step reaches.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/savi_speed.py [--variant=paper|small|tiny] [--steps=3] \
      [--set savi.pool=2 --set "savi.decoder.strides=(2, 2)" ...]

Times the jitted pretrain step (forward, backward, Adam) at batch 8 x 6 frames of 64x64 with the variant's SAVi
(paper = SAVi-S), prints its parameter count (and :paper's), frames/s, the step's FLOPs from XLA's cost analysis
of the compiled step, and the ratio of the step's FLOP/s to the FLOP/s of a large float32 matmul measured in the
same run.
"""
import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import flops  # pylint: disable=wrong-import-position  (benchmarks/flops.py)
from configs import common  # pylint: disable=wrong-import-position
from roboshape.models import savi  # pylint: disable=wrong-import-position
from roboshape.train import pretrain  # pylint: disable=wrong-import-position


def synthetic_inputs(comp, shape):
  """(state, video, depth, first, key) for a pretrain step (pretrain.Compiled) on random uint8 clips of `shape` [B,
  T, H, W, 3], placed as the pretrain stage places them: the state replicated, the batch split. `depth` is the depth
  target (uint16 mm) of a variant that predicts depth (:small), else None; `first` the clips' first segmentation
  [B, H, W] (random ids) of a conditional SAVi, else None."""
  state = jax.device_put(comp.init_state(jax.random.key(0), shape), comp.dp.replicated)
  rng = np.random.default_rng(0)
  video = jax.device_put(rng.integers(0, 256, shape, dtype=np.uint8), comp.dp.batch)
  depth = None
  if comp.depth_weight > 0:
    depth = jax.device_put(rng.integers(300, 2000, shape[:-1], dtype=np.uint16), comp.dp.batch)
  first = None
  if comp.conditional:
    first = jax.device_put(rng.integers(0, comp.model.num_slots, (shape[0], *shape[2:4]), dtype=np.uint8),
                           comp.dp.batch)
  return state, video, depth, first, jax.random.key(1)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--variant", default="paper", choices=common.VARIANTS)
  parser.add_argument("--steps", type=int, default=3, help="timed steps after one warm-up step")
  parser.add_argument("--batch", type=int, default=8)
  parser.add_argument("--frames", type=int, default=6)
  parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                      help="override a config field (a Python literal), e.g. --set savi.pool=2")
  args = parser.parse_args()

  config = common.get_config("pick", "savi", args.variant)
  for item in args.set:
    common.override(config, item)
  config.env.resolution = 64
  config.pretrain.train.batch_size = args.batch
  config.pretrain.train.clip_length = args.frames
  pretrain.validate_config(config)
  comp = pretrain.compiled(config)
  state, video, depth, first, key = synthetic_inputs(comp, (args.batch, args.frames, 64, 64, 3))

  start = time.perf_counter()
  compiled = comp.train_step.lower(state, video, depth, first, key).compile()
  compile_s = time.perf_counter() - start
  step_flops = flops.step_flops(comp.train_step, state, video, depth, first, key)

  state, metrics = compiled(state, video, depth, first, key)
  jax.block_until_ready(metrics)
  times = []
  for _ in range(args.steps):
    start = time.perf_counter()
    state, metrics = compiled(state, video, depth, first, key)
    jax.block_until_ready(metrics)
    times.append(time.perf_counter() - start)
  step_s = float(np.median(times))
  matmul = flops.matmul_flops_per_s()

  frames = args.batch * args.frames
  params = savi.parameter_count(config.savi, 64)
  paper_params = savi.parameter_count(common.get_config("pick", "savi", "paper").savi, 64)
  print(f"device: {jax.devices()[0].device_kind} x{jax.device_count()}, variant {args.variant}, "
        f"batch {args.batch} x {args.frames} frames, 64x64, K={config.savi.num_slots}, D={config.savi.slot_size}")
  print(f"parameters: {params:,} ({args.variant}{' with --set' if args.set else ''}); :paper (SAVi-S) "
        f"{paper_params:,}")
  print(f"compile: {compile_s:.1f} s; step times (s): {', '.join(f'{t:.3f}' for t in times)}")
  print(f"train step: {step_s:.3f} s median -> {frames / step_s:.1f} frames/s")
  print(f"step FLOPs (XLA cost analysis): {step_flops / 1e9:.1f} GFLOP -> {step_flops / step_s / 1e9:.1f} GFLOP/s")
  print(f"dense matmul 2048^3 float32: {matmul / 1e9:.1f} GFLOP/s")
  print(f"ratio step FLOP/s / matmul FLOP/s: {step_flops / step_s / matmul:.3f}")


if __name__ == "__main__":
  main()
