"""Success rate of the oracle experts: every task under every level, over N seeds, within the task's horizon.

  .venv/bin/python benchmarks/expert_success.py [--seeds 100] [--tasks push,pick,place] [--levels train,L1,L2,L3]
                                                [--noise 0.2]

--noise S adds Gaussian noise of std S to the arm's six action dimensions (not the gripper), drawn from a generator
seeded by the env seed: the expert's success when its actions carry errors like those a policy adds, i.e. how
precise a policy imitating it has to be.

Runs without a camera (obs_mode state: the physics alone, no rendering) since the expert reads simulator state only.
Prints one row per task x level: success %, episode length p50 / p95 / max over successful episodes, the horizon and
whether it is >= 1.5x the p95 length. Seeds start at --first_seed (default 1_000_000, away from dataset seeds).
"""
import argparse
import os
import sys
import time

import numpy as np
import torch
import tqdm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from roboshape import envs  # pylint: disable=wrong-import-position
from roboshape.envs import experts  # pylint: disable=wrong-import-position


def run_expert(env, expert, seed: int, horizon: int, noise: float = 0.0):
  """One expert episode, its arm actions with Gaussian noise of std `noise`; returns (success, steps)."""
  env.reset(seed=seed)
  expert.reset()
  task = env.unwrapped
  rng = np.random.default_rng([seed, 7])
  for step in range(1, horizon + 1):
    action = expert.act(task.privileged_state())
    if noise:
      jitter = noise * rng.normal(size=action.shape)
      jitter[:, 6] = 0.0
      action = (action + torch.as_tensor(jitter, dtype=action.dtype)).clamp(-1, 1)
    _, _, _, _, info = env.step(action)
    if bool(info["success"][0]):
      return True, step
  return False, horizon


def main():
  parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--seeds", type=int, default=100)
  parser.add_argument("--first_seed", type=int, default=1_000_000)
  parser.add_argument("--tasks", default=",".join(envs.TASKS))
  parser.add_argument("--levels", default=",".join(envs.LEVEL_NAMES))
  parser.add_argument("--noise", type=float, default=0.0, help="std of the noise added to the arm's actions")
  parser.add_argument("--verbose", action="store_true", help="print every failed seed")
  args = parser.parse_args()
  rows = []
  for task in args.tasks.split(","):
    for level in args.levels.split(","):
      env = envs.make_env(task, level, obs_mode="state")
      horizon = env.unwrapped.HORIZON
      expert = experts.make_expert(task, 1)
      results, start = [], time.time()
      for seed in tqdm.trange(args.first_seed, args.first_seed + args.seeds, desc=f"{task}/{level}", leave=False):
        ok, steps = run_expert(env, expert, seed, horizon, args.noise)
        results.append((ok, steps))
        if not ok and args.verbose:
          print(f"  failed: {task} {level} seed {seed}", flush=True)
      env.close()
      lengths = np.array([s for ok, s in results if ok] or [0])
      success = 100.0 * np.mean([ok for ok, _ in results])
      p95 = float(np.percentile(lengths, 95))
      rows.append((task, level, success, np.percentile(lengths, 50), p95, lengths.max(), horizon,
                   horizon >= 1.5 * p95, (time.time() - start) / len(results)))
      print(f"{task:5s} {level:5s} success {success:5.1f}%  done in {time.time() - start:.0f}s", flush=True)
  print(f"\nOracle expert success over {args.seeds} seeds (from {args.first_seed}), within the task horizon"
        + (f", arm actions + N(0, {args.noise}^2) noise" if args.noise else ""))
  print("| task | level | success % | len p50 | len p95 | len max | horizon | horizon >= 1.5 x p95 | s/episode |")
  print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
  for task, level, success, p50, p95, mx, horizon, ok, spe in rows:
    print(f"| {task} | {level} | {success:.1f} | {p50:.0f} | {p95:.1f} | {mx} | {horizon} | {'yes' if ok else 'NO'} "
          f"| {spe:.2f} |")


if __name__ == "__main__":
  main()
