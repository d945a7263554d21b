"""Env steps per second of a RoboShape task, with and without rendering, random actions, one env, this process.

  .venv/bin/python benchmarks/env_speed.py [--task pick] [--resolution 64] [--steps 200]

Modes, measured one after the other in the same run: state (no camera), rgb (64x64 front camera),
rgb+segmentation (what SimPool workers use) and rgb+depth+segmentation (what they use with env.depth, at `:small`). Also prints the cost of a reset (each reset rebuilds the scene).
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from roboshape import envs  # pylint: disable=wrong-import-position


def measure(task: str, obs_mode: str, resolution: int, steps: int, resets: int):
  import torch  # pylint: disable=import-outside-toplevel
  env = envs.make_env(task, "train", resolution=resolution, obs_mode=obs_mode)
  rng = np.random.default_rng(0)
  env.reset(seed=0)
  for _ in range(5):  # warm up (first render compiles shaders)
    env.step(torch.as_tensor(rng.uniform(-1, 1, (1, 7)), dtype=torch.float32))
  start = time.perf_counter()
  for _ in range(steps):
    env.step(torch.as_tensor(rng.uniform(-1, 1, (1, 7)), dtype=torch.float32))
  step_s = (time.perf_counter() - start) / steps
  start = time.perf_counter()
  for seed in range(1, resets + 1):
    env.reset(seed=seed)
  reset_s = (time.perf_counter() - start) / resets
  env.close()
  return step_s, reset_s


def main():
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--task", default="pick", choices=envs.TASKS)
  parser.add_argument("--resolution", type=int, default=64)
  parser.add_argument("--steps", type=int, default=200)
  parser.add_argument("--resets", type=int, default=10)
  args = parser.parse_args()
  rows = []
  for mode in ("state", "rgb", "rgb+segmentation", "rgb+depth+segmentation"):
    step_s, reset_s = measure(args.task, mode, args.resolution, args.steps, args.resets)
    rows.append((mode, step_s, reset_s))
  print(f"\n{args.task}, {args.resolution}x{args.resolution}, one env, physx_cpu, random pd_ee_delta_pose actions, "
        f"{args.steps} steps, {os.cpu_count()} CPU cores")
  print("| obs mode | ms / step | steps / s | x state | ms / reset |")
  print("| --- | --- | --- | --- | --- |")
  for mode, step_s, reset_s in rows:
    print(f"| {mode} | {1000 * step_s:.1f} | {1 / step_s:.0f} | {step_s / rows[0][1]:.1f} | {1000 * reset_s:.0f} |")


if __name__ == "__main__":
  main()
