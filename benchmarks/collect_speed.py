"""Collection speed of the RoboShape dataset against the raw simulator, measured side by side in one run.

  .venv/bin/python benchmarks/collect_speed.py [--task pick|push|place|all] [--episodes 8] [--workers 0]
                                               [--raw-steps 200] [--resolution 64] [--cameras]

--cameras measures only the cost of the wrist camera: the collect path with 1 worker (with depth, as `:small`
collects) with the front camera alone and with the front and the wrist camera, the two runs taking turns
(front, both, front, both), and prints seconds and bytes per episode and their ratio.

Prints, at --resolution (64) with rendering (RGB + segmentation):
  raw env   : env steps/s of one env in one process, random actions, no expert, no bridge, no writing
              (a fresh process that imports the simulator only, as a worker does), measured twice: resetting at
              the task's horizon (random actions never succeed), and resetting every L steps, L the mean length
              of the expert's episodes in the collect run, so that both sides pay the same resets and the ratio
              isolates the expert, the bridge and the writing;
  collect 1 : frames/s of the collect path with 1 worker (SimPool expert episodes -> this process -> TFDS shards),
              simulator start-up excluded, writing included;
  collect N : the same with N workers (--workers, 0 = one per CPU core);
and the ratios against the bars of the dataset issue (collect 1 >= 0.8 x raw; collect N >= 0.8 N x collect 1 on
N cores), the storage per 1000 frames, episodes per hour, the expert's success rate, and the time the paper-scale
set (3 tasks x 2000 train + 5% val episodes) would take with 1 and with N workers at the measured rates.
"""
import argparse
import gc
import multiprocessing
import os
import shutil
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def _raw_rate(task: str, resolution: int, steps: int, episode_lengths, queue) -> None:
  """Child process: steps/s of one env with random actions, once per episode length (0: the task's horizon).

  An episode of length L renders L frames: the reset's and L - 1 steps'. Puts ([frames/s per length], reset s).
  """
  import numpy as np  # pylint: disable=import-outside-toplevel
  import torch  # pylint: disable=import-outside-toplevel
  torch.set_num_threads(1)
  from roboshape import envs  # pylint: disable=import-outside-toplevel
  env = envs.make_env(task, "train", resolution=resolution)
  unwrapped = env.unwrapped
  gc.freeze()  # as a sim worker does after start-up (roboshape/sim/worker.py): cheaper resets
  rng = np.random.default_rng(0)
  obs, _ = env.reset(seed=0)
  unwrapped.frames(obs)
  for _ in range(10):  # warm-up: shader compilation, first contacts
    obs, *_ = env.step(torch.as_tensor(rng.uniform(-1, 1, (1, 7)), dtype=torch.float32))
  rates, resets = [], 0
  for length in episode_lengths:
    length = length or unwrapped.HORIZON + 1
    start, frames, episode_frames = time.perf_counter(), 0, 1
    while frames < steps:
      if episode_frames >= length:
        obs, _ = env.reset(seed=1 + resets)
        resets += 1
        episode_frames = 0
      else:
        obs, *_ = env.step(torch.as_tensor(rng.uniform(-1, 1, (1, 7)), dtype=torch.float32))
      unwrapped.frames(obs)
      frames += 1
      episode_frames += 1
    rates.append(frames / (time.perf_counter() - start))
  start = time.perf_counter()
  for seed in range(100, 103):
    unwrapped.frames(env.reset(seed=seed)[0])
  queue.put((rates, (time.perf_counter() - start) / 3))


def raw_env_rate(task: str, resolution: int, steps: int, episode_lengths=(0,)):
  """([frames/s with random actions per episode length], seconds per env.reset) of one env in a fresh process."""
  ctx = multiprocessing.get_context("spawn")
  queue = ctx.Queue()
  proc = ctx.Process(target=_raw_rate, args=(task, resolution, steps, tuple(episode_lengths), queue))
  proc.start()
  rates = queue.get(timeout=3600)
  proc.join()
  return rates


def collect_rate(config, workers: int, workdir: str) -> dict:
  """Collects config.data.train_episodes (+ val) with `workers` workers; frames/s excluding simulator start-up."""
  from roboshape.data import collect  # pylint: disable=import-outside-toplevel
  from roboshape.data import dataset_path  # pylint: disable=import-outside-toplevel
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel
  path = dataset_path(config, workdir)
  with SimPool(EnvSpec.from_config(config), num_workers=workers) as pool:
    start = time.perf_counter()
    report = collect.collect_dataset(pool, path, collect.config_summary(config), collect.split_targets(config),
                                     progress=False)
    seconds = time.perf_counter() - start
  state = rlds.load_state(path)
  shards = [s for split in state["splits"].values() for s in split["shards"]]
  stored_frames = sum(s["num_steps"] for s in shards)
  episodes = sum(len(s["seeds"]) for s in shards)
  failures = sum(len(s["failed_seeds"]) for s in shards)
  frames = sum(report[split]["frames"] for split in ("train", "val"))  # rendered, failed episodes included
  return {"frames_per_s": frames / seconds, "episodes_per_h": 3600 * episodes / seconds, "episodes": episodes,
          "failures": failures, "seconds": seconds, "bytes_per_frame": sum(s["num_bytes"] for s in shards) /
          stored_frames, "frames_per_episode": stored_frames / episodes}


def compare_cameras(common, args) -> int:
  """Collection with the front camera alone against the front and the wrist camera, 1 worker, in turns."""
  print(f"machine: {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f} at start; resolution "
        f"{args.resolution}, depth stored, 1 worker, {args.episodes} + 1 episodes a run", flush=True)
  tasks = ("push", "pick", "place") if args.task == "all" else (args.task,)
  for task in tasks:
    runs = {("front",): [], ("front", "wrist"): []}
    for cameras in list(runs) * 2:
      config = common.get_config(task, "savi", "tiny")
      config.env.resolution, config.env.depth, config.env.cameras = args.resolution, True, cameras
      config.data.train_episodes = args.episodes
      workdir = tempfile.mkdtemp(prefix="roboshape_bench_")
      try:
        r = collect_rate(config, 1, workdir)
      finally:
        shutil.rmtree(workdir, ignore_errors=True)
      runs[cameras].append(r)
      print(f"[{task}] {' + '.join(cameras):13s}: {r['seconds'] / r['episodes']:.2f} s/episode, "
            f"{r['frames_per_s']:.1f} frames/s, {r['bytes_per_frame'] * r['frames_per_episode'] / 1e3:.0f} KB/episode",
            flush=True)
    per_episode = {c: sum(r["seconds"] for r in rs) / sum(r["episodes"] for r in rs) for c, rs in runs.items()}
    size = {c: sum(r["bytes_per_frame"] for r in rs) / len(rs) for c, rs in runs.items()}
    one, two = per_episode[("front",)], per_episode[("front", "wrist")]
    print(f"[{task}] ratio front + wrist / front per collected episode: {two / one:.2f} ({two:.2f} s against "
          f"{one:.2f} s; bar <= 2); bytes per frame {size[('front', 'wrist')] / size[('front',)]:.2f}x", flush=True)
  return 0


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--task", default="pick", choices=("push", "pick", "place", "all"))
  parser.add_argument("--episodes", type=int, default=8, help="train episodes per collection run (+1 val)")
  parser.add_argument("--workers", type=int, default=0, help="N for the parallel run (0: one per CPU core)")
  parser.add_argument("--raw-steps", type=int, default=200, help="timed random-action env steps")
  parser.add_argument("--resolution", type=int, default=64)
  parser.add_argument("--cameras", action="store_true", help="front alone against front + wrist, 1 worker")
  args = parser.parse_args(argv)
  from configs import common  # pylint: disable=import-outside-toplevel
  if args.cameras:
    return compare_cameras(common, args)
  workers = args.workers or os.cpu_count() or 1
  tasks = ("push", "pick", "place") if args.task == "all" else (args.task,)
  print(f"machine: {os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f} at start; "
        f"resolution {args.resolution}; N = {workers} workers", flush=True)
  hours_1 = hours_n = 0.0
  for task in tasks:
    config = common.get_config(task, "savi", "tiny")
    config.env.resolution = args.resolution
    config.data.train_episodes = args.episodes
    results = {}
    for n in sorted({1, workers}):
      workdir = tempfile.mkdtemp(prefix="roboshape_bench_")
      try:
        results[n] = r = collect_rate(config, n, workdir)
      finally:
        shutil.rmtree(workdir, ignore_errors=True)
      print(f"[{task}] collect {n:2d}w  : {r['frames_per_s']:7.1f} frames/s, {r['episodes_per_h']:6.0f} episodes/h "
            f"({r['episodes']} kept, {r['failures']} expert failures, {r['frames_per_episode']:.0f} frames/episode, "
            f"{r['seconds']:.0f}s)", flush=True)
    one, many = results[1], results[workers]
    length = max(1, round(one["frames_per_episode"]))
    (raw_horizon, raw), reset_s = raw_env_rate(task, args.resolution, args.raw_steps, (0, length))
    print(f"[{task}] raw env      : {raw_horizon:7.1f} frames/s resetting at the horizon, {raw:.1f} frames/s resetting "
          f"every {length} frames as the expert's episodes do (1 env, random actions, no writing); "
          f"env.reset {reset_s:.2f}s", flush=True)
    print(f"[{task}] ratio collect 1w / raw env = {one['frames_per_s'] / raw:.2f} with the same resets (bar >= 0.80; "
          f"the expert, bridge and writing); {one['frames_per_s'] / raw_horizon:.2f} against the raw env resetting "
          "at the horizon only")
    if workers > 1:
      print(f"[{task}] ratio collect {workers}w / 1w   = {many['frames_per_s'] / one['frames_per_s']:.2f} "
            f"(bar >= {0.8 * workers:.2f})")
    print(f"[{task}] storage: {one['bytes_per_frame']:.0f} bytes/frame, {one['bytes_per_frame'] / 1e3:.2f} MB per "
          "1000 frames (image PNG + segmentation zlib + step fields)", flush=True)
    success = one["episodes"] / max(1, one["episodes"] + one["failures"])
    paper_episodes = 2000 + 100
    hours_1 += paper_episodes / one["episodes_per_h"]
    hours_n += paper_episodes / many["episodes_per_h"]
    print(f"[{task}] expert success {100 * success:.0f}%; 2000 + 100 episodes: "
          f"{paper_episodes / one['episodes_per_h']:.1f} h with 1 worker, "
          f"{paper_episodes / many['episodes_per_h']:.1f} h with {workers}", flush=True)
  if len(tasks) == 3:
    print(f"paper scale, 3 x (2000 + 100) episodes: {hours_1:.1f} h with 1 worker, {hours_n:.1f} h with {workers} "
          f"workers (load average now {os.getloadavg()[0]:.1f})")
  return 0


if __name__ == "__main__":
  sys.exit(main())
