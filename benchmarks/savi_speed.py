"""SAVi train-step throughput, and how much of the machine's dense-matmul speed the step reaches.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/savi_speed.py [--variant=paper|small|tiny] [--steps=3] \
      [--set savi.pool=2 --set "savi.decoder.strides=(2, 2)" ...] [--compare]

Times the jitted pretrain step (forward, backward, Adam) at batch 8 x 6 frames of 64x64 with the variant's SAVi
(paper = SAVi-S), prints its parameter count (and :paper's), frames/s, the step's FLOPs from XLA's cost analysis
of the compiled step (a scan over frames is counted once, not once a frame), and the ratio of the step's FLOP/s to
the FLOP/s of a large float32 matmul measured in the same run. --compare also times the plain variant, its steps
taking turns with the --set ones, and prints the ratio of the two steps' times.
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
  """(state, video, depth, first, key, pixel_weight) for a pretrain step (pretrain.Compiled) on random uint8 clips of `shape` [B,
  T, H, W, 3], placed as the pretrain stage places them: the state replicated, the batch split. `depth` is the depth
  target (uint16 mm) of a variant that predicts depth (:small), else None; `first` the clips' first segmentation
  [B, H, W] (random ids) of a conditional SAVi, else None; then, where pretrain.train.mask_weight > 0 (:small), the
  pixel weights [B, T, H, W]: ones, as the step's arithmetic does not depend on their values (the pretrain stage
  computes them on the host from the segmentation), else None."""
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
  weight = None
  if comp.mask_weight > 0:
    weight = jax.device_put(np.ones(shape[:-1], np.float32), comp.dp.batch)
  return state, video, depth, first, jax.random.key(1), weight


class Timed:
  """One config's compiled pretrain step on synthetic clips: `step()` runs it once and returns its seconds."""

  def __init__(self, config, shape):
    pretrain.validate_config(config)
    comp = pretrain.compiled(config)
    self.state, *self.inputs = synthetic_inputs(comp, shape)
    start = time.perf_counter()
    self.compiled = comp.train_step.lower(self.state, *self.inputs).compile()
    self.compile_s = time.perf_counter() - start
    self.flops = flops.step_flops(comp.train_step, self.state, *self.inputs)
    self.times = []
    self.step()                                                     # warm-up, not kept
    self.times = []

  def step(self) -> float:
    start = time.perf_counter()
    self.state, metrics = self.compiled(self.state, *self.inputs)
    jax.block_until_ready(metrics)
    self.times.append(time.perf_counter() - start)
    return self.times[-1]

  @property
  def median(self) -> float:
    return float(np.median(self.times))


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--variant", default="paper", choices=common.VARIANTS)
  parser.add_argument("--steps", type=int, default=3, help="timed steps after one warm-up step")
  parser.add_argument("--batch", type=int, default=8)
  parser.add_argument("--frames", type=int, default=6)
  parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                      help="override a config field (a Python literal), e.g. --set savi.pool=2")
  parser.add_argument("--compare", action="store_true",
                      help="also time the plain variant, taking turns, and print the ratio of the step times")
  args = parser.parse_args()

  def config_of(sets):
    config = common.get_config("pick", "savi", args.variant)
    for item in sets:
      common.override(config, item)
    config.env.resolution = 64
    config.pretrain.train.batch_size = args.batch
    config.pretrain.train.clip_length = args.frames
    return config

  shape = (args.batch, args.frames, 64, 64, 3)
  config = config_of(args.set)
  runs = {"with --set" if args.set else args.variant: Timed(config, shape)}
  if args.compare:
    runs[f"plain {args.variant}"] = Timed(config_of([]), shape)
  for _ in range(args.steps):
    for run in runs.values():
      run.step()
  matmul = flops.matmul_flops_per_s()

  frames = args.batch * args.frames
  params = savi.parameter_count(config.savi, 64)
  paper_params = savi.parameter_count(common.get_config("pick", "savi", "paper").savi, 64)
  print(f"device: {jax.devices()[0].device_kind} x{jax.device_count()}, variant {args.variant}, "
        f"batch {args.batch} x {args.frames} frames, 64x64, K={config.savi.num_slots}, D={config.savi.slot_size}")
  print(f"parameters: {params:,} ({args.variant}{' with --set ' + ' '.join(args.set) if args.set else ''}); "
        f":paper (SAVi-S) {paper_params:,}")
  for name, run in runs.items():
    print(f"[{name}] compile: {run.compile_s:.1f} s; step times (s): {', '.join(f'{t:.3f}' for t in run.times)}")
    print(f"[{name}] train step: {run.median:.3f} s median -> {frames / run.median:.1f} frames/s")
    print(f"[{name}] step FLOPs (XLA cost analysis): {run.flops / 1e9:.1f} GFLOP -> "
          f"{run.flops / run.median / 1e9:.1f} GFLOP/s; / matmul FLOP/s: {run.flops / run.median / matmul:.3f}")
  print(f"dense matmul 2048^3 float32: {matmul / 1e9:.1f} GFLOP/s")
  if args.compare:
    (_, candidate), (_, plain) = runs.items()
    print(f"ratio step with --set / plain {args.variant} step: {candidate.median / plain.median:.2f} "
          f"(medians of {args.steps} turns each)")


if __name__ == "__main__":
  main()
