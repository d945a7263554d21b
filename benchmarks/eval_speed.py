"""Closed-loop evaluation throughput: the SAVi policy vs the oracle expert driving the same simulator workers.

  .venv/bin/python benchmarks/eval_speed.py [--task push] [--variant small] [--workers 0] [--episodes 8] [--cameras]

--cameras measures only the cost of the wrist camera in evaluation: the same SAVi policy (random weights) reading
the front camera alone and reading the front and the wrist views (roboshape/encoders/views.py, as a `+wrist` column
runs), each in its own pool of one worker rendering its cameras, the two taking turns on the same seeds; prints
seconds per rollout step of each and their ratio.

In one pool (same workers, same run), alternately:
  expert: `pool.collect(seeds)` (the oracle expert steps the envs inside the workers), env steps/s;
  policy: `closed_loop.run_rollouts` with a SAVi + transformer policy of the variant's architecture and random
          weights (speed does not depend on the weights): the policy runs in this process, batched over the
          pool's envs, exactly as the evaluate stage runs it. Env steps/s counts only live env steps.
Each is measured `--rounds` times, alternately (expert, policy, expert, policy, ...), and the best of each kept, to
damp the noise of a shared machine (the expert's own rate varies between rounds). Prints both rates, their
ratio (the bar: >= 0.8 on a 2-core CPU), the policy's own cost per batched step, and what the paper's evaluation
grid (3 tasks x 3 encoders x 4 levels x 300 rollouts) would take at the measured rate.
Then the simulator alone, the same envs stepped with the same actions, rendered (what a camera policy's rollouts
cost) and not rendered (what a `state` policy's unrecorded rollouts cost: `pool.reset(seeds, render=False)`).
"""
import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position

from configs import common  # pylint: disable=wrong-import-position
from roboshape.encoders import views  # pylint: disable=wrong-import-position
from roboshape.envs import camera as camera_lib  # pylint: disable=wrong-import-position
from roboshape.eval import closed_loop  # pylint: disable=wrong-import-position


def random_savi_policy(config):
  """A `Policy` (models/policy.py) over a randomly initialised SAVi encoder, with the config's architectures."""
  # pylint: disable=import-outside-toplevel
  import functools
  import jax.numpy as jnp
  from roboshape.models import policy as policy_lib
  from roboshape.models.encoder import FrozenEncoder
  from roboshape.train import bc
  from roboshape.models import savi
  from roboshape.train import pretrain
  comp = pretrain.compiled(config)
  r = config.env.resolution
  params = comp.init_state(jax.random.key(0), (1, config.pretrain.train.clip_length, r, r, 3))["params"]
  init = savi.initial_slots(comp.model, params, 1)[0]
  encoder = FrozenEncoder(
      name="savi", params=params, step=functools.partial(savi.frozen_step, comp.model),
      init_state=lambda b: jnp.broadcast_to(init, (b, *init.shape)), num_tokens=comp.model.num_slots,
      token_dim=comp.model.slot_size, identity="savi:random")
  encoder = views.with_views(encoder, config.env.cameras)        # itself with one camera
  net = policy_lib.net_from_config(config.policy)
  state = bc.init_state(net, bc.make_optimizer(config.policy.train),
                        (1, config.policy.history, encoder.num_tokens, encoder.token_dim), 0)
  spec = policy_lib.ControlSpec(history=config.policy.history)
  return policy_lib.Policy(net, state["params"], encoder, spec, np.ones(7, np.float32), np.zeros(7, np.float32))


def time_expert(pool, seeds):
  start = time.perf_counter()
  steps = lengths = 0
  for episode in pool.collect(seeds):
    steps += len(episode["action"])
    lengths += 1
  return steps / (time.perf_counter() - start), steps / max(lengths, 1)


def time_policy(pool, policy, seeds):
  lengths = []
  plan = [closed_loop.Rollout("train", 0, i, s) for i, s in enumerate(seeds)]
  start = time.perf_counter()
  closed_loop.run_rollouts(pool, policy, plan, lambda r, res, fr: lengths.append(res["length"]), desc="policy")
  return sum(lengths) / (time.perf_counter() - start), float(np.mean(lengths))


def time_env(pool, seeds, render, steps):
  """Env steps/s of the pool's envs reset from `seeds` and stepped `steps` times with zero actions."""
  pool.reset(seeds, render=[render] * len(seeds))
  actions = np.zeros((len(seeds), 7), np.float32)
  start = time.perf_counter()
  for _ in range(steps):
    pool.step(actions)
  return steps * len(seeds) / (time.perf_counter() - start)


def compare_cameras(args) -> None:
  """The --cameras measurement (module docstring): front alone against front + wrist, alternating rounds."""
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel
  settings = {"front": camera_lib.DEFAULT, "front + wrist": (camera_lib.FRONT, camera_lib.WRIST)}
  configs = {}
  for label, cameras in settings.items():
    config = common.get_config(args.task, "savi", args.variant)
    config.env.max_episode_steps = args.max_steps
    config.env.cameras = cameras
    configs[label] = config
  print(f"task {args.task}, SAVi+policy of variant {args.variant!r} (random weights), one worker a setting, "
        f"{os.cpu_count()} CPUs", flush=True)
  seconds = {label: [] for label in settings}
  with SimPool(EnvSpec.from_config(configs["front"], level="train"), num_workers=1) as front, \
       SimPool(EnvSpec.from_config(configs["front + wrist"], level="train"), num_workers=1) as both:
    pools = {"front": front, "front + wrist": both}
    policies = {label: random_savi_policy(configs[label]) for label in settings}
    episodes = args.episodes or 2 * front.num_envs
    for label, pool in pools.items():                # warm-up: worker start, shaders, the policy's compilation
      time_policy(pool, policies[label], [2 * 10**9 + i for i in range(pool.num_envs)])
    for rep in range(args.rounds):
      seeds = [10**9 + 800_000 + rep * 10_000 + i for i in range(episodes)]
      for label, pool in pools.items():
        rate, _ = time_policy(pool, policies[label], seeds)
        seconds[label].append(1.0 / rate)
      print(f"  round {rep + 1}: " + ", ".join(f"{label} {1e3 * s[-1]:.1f} ms/step" for label, s in seconds.items()),
            flush=True)
  one, two = (min(seconds[label]) for label in settings)
  print(f"per rollout step (best of {args.rounds}): front {1e3 * one:.1f} ms, front + wrist {1e3 * two:.1f} ms")
  print(f"ratio front + wrist / front per evaluated episode: {two / one:.2f} (bar <= 2: "
        f"{'PASS' if two / one <= 2 else 'FAIL'})")


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--task", default="push", choices=common.TASKS)
  parser.add_argument("--variant", default="small", choices=common.VARIANTS)
  parser.add_argument("--workers", type=int, default=0, help="sim workers (0: one per core)")
  parser.add_argument("--episodes", type=int, default=0, help="episodes per measurement (0: 2 per env)")
  parser.add_argument("--max-steps", type=int, default=0, help="episode step limit (0: the task's horizon)")
  parser.add_argument("--rounds", type=int, default=3, help="alternating expert/policy measurements")
  parser.add_argument("--cameras", action="store_true", help="only the wrist camera's cost (module docstring)")
  args = parser.parse_args()
  if args.cameras:
    compare_cameras(args)
    return
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel

  config = common.get_config(args.task, "savi", args.variant)
  config.env.max_episode_steps = args.max_steps
  policy = random_savi_policy(config)
  spec = EnvSpec.from_config(config, level="train")
  print(f"task {args.task}, SAVi+policy of variant {args.variant!r} (random weights), jax on "
        f"{jax.devices()[0].platform}, {os.cpu_count()} CPUs", flush=True)
  with SimPool(spec, num_workers=args.workers) as pool:
    n = pool.num_envs
    episodes = args.episodes or 2 * n
    # Warm-up: worker start, shaders, the policy's compilation for this batch size.
    policy.reset(batch_size=n)
    frames = pool.reset([10**9 + 900_000 + i for i in range(n)])["image"]
    for _ in range(3):
      pool.step(np.clip(policy.act_batch(frames), -1, 1))
    list(pool.collect([2 * 10**9 + i for i in range(n)]))
    t0 = time.perf_counter()
    for _ in range(20):
      jax.block_until_ready(policy.act_batch(frames))
    act_ms = (time.perf_counter() - t0) / 20 * 1e3

    expert, policy_rates, expert_len, policy_len = [], [], 0.0, 0.0
    for rep in range(args.rounds):
      base = 10**9 + 800_000 + rep * 10_000
      rate, expert_len = time_expert(pool, [base + i for i in range(episodes)])
      expert.append(rate)
      rate, policy_len = time_policy(pool, policy, [base + 5_000 + i for i in range(episodes)])
      policy_rates.append(rate)
      print(f"  round {rep + 1}: expert {expert[-1]:.1f} env steps/s, SAVi policy {policy_rates[-1]:.1f} env "
            f"steps/s", flush=True)
    seeds = [10**9 + 700_000 + i for i in range(n)]
    camera = max(time_env(pool, seeds, True, 60) for _ in range(2))
    blind = max(time_env(pool, seeds, False, 60) for _ in range(2))
  e, p = max(expert), max(policy_rates)
  print(f"envs in the pool: {n}; episodes per measurement: {episodes}")
  print(f"policy act_batch alone (B={n}, no simulator): {act_ms:.1f} ms per batched step")
  print(f"expert: {e:.1f} env steps/s (mean episode {expert_len:.0f} steps)")
  print(f"SAVi policy: {p:.1f} env steps/s (mean episode {policy_len:.0f} steps, random weights: mostly horizon)")
  print(f"ratio policy/expert: {p / e:.2f} (bar >= 0.8: {'PASS' if p / e >= 0.8 else 'FAIL'})")
  print(f"simulator alone: rendered {camera:.1f} env steps/s, not rendered {blind:.1f} env steps/s "
        f"({blind / camera:.1f}x: a `state` policy's unrecorded rollouts)")
  rollouts = 3 * 3 * 4 * 300
  for label, length in (("every rollout runs to the horizon", policy_len), ("rollouts as long as the expert's",
                                                                             expert_len)):
    hours = rollouts * length / p / 3600
    print(f"paper grid ({rollouts} rollouts), {label} ({length:.0f} steps): {hours:.1f} h at {p:.1f} env steps/s")


if __name__ == "__main__":
  main()
