"""XLA:CPU's two kernel emitters side by side: compile seconds and step times of a SAVi and a policy train step.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/xla_emitters.py [--variant tiny | --suite] [--steps 10]

XLA reads its flags once a process, so each case runs in a child process of this script, one after another:
{XLA's MLIR fusion emitters (its default), its older emitters (--xla_cpu_use_fusion_emitters=false, which
tests/conftest.py sets for the test suite)} x {XLA's default optimisation level, its cheap one
(jax_disable_most_optimizations, the suite's `cheap_compiles`)}, each on one host device. A child compiles the
variant's SAVi pretrain step and its BC train step (batch, clip and history from the variant's config; as many
tokens as SAVi has slots), then times `--steps` chained steps of each after one warm-up step. --suite takes the
test suite's SAVi instead (tests/test_savi.py `tiny_config`: 16x16 frames, one clip a batch), the kind of program
the suite compiles. The table gives each case's compile seconds and median step milliseconds, and their ratios to
the default case's.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CASES = {  # name: (XLA_FLAGS added, jax_disable_most_optimizations)
    "fusion emitters, default level": ("", False),
    "fusion emitters, cheap level": ("", True),
    "older emitters, default level": ("--xla_cpu_use_fusion_emitters=false", False),
    "older emitters, cheap level": ("--xla_cpu_use_fusion_emitters=false", True),
}


def _timed(fn, args, steps: int):
  """(compile seconds, median seconds a step) of jitted `fn` chained over `steps` steps from `args`."""
  import jax  # pylint: disable=import-outside-toplevel
  start = time.perf_counter()
  compiled = fn.lower(*args).compile()
  compile_s = time.perf_counter() - start
  state, rest = args[0], args[1:]
  times = []
  for _ in range(steps + 1):                            # the first is a warm-up
    start = time.perf_counter()
    state, metrics = compiled(state, *rest)
    jax.block_until_ready(metrics)
    times.append(time.perf_counter() - start)
  return compile_s, statistics.median(times[1:])


def child(variant: str, suite: bool, cheap: bool, steps: int) -> dict:
  """This process's case: {"savi": (compile s, step s), "policy": (compile s, step s)}."""
  sys.path[:0] = [ROOT, os.path.join(ROOT, "benchmarks"), os.path.join(ROOT, "tests")]
  import jax  # pylint: disable=import-outside-toplevel
  jax.config.update("jax_disable_most_optimizations", cheap)
  import bc_speed  # pylint: disable=import-outside-toplevel  (benchmarks/bc_speed.py)
  import savi_speed  # pylint: disable=import-outside-toplevel  (benchmarks/savi_speed.py)
  from configs import common  # pylint: disable=import-outside-toplevel
  from roboshape.train import pretrain  # pylint: disable=import-outside-toplevel
  assert jax.device_count() == 1, jax.devices()
  if suite:
    import test_savi  # pylint: disable=import-outside-toplevel  (tests/test_savi.py)
    config = test_savi.tiny_config()
  else:
    config = common.get_config("push", "savi", variant)
  t, r = config.pretrain.train, config.env.resolution
  comp = pretrain.compiled(config)
  savi_args = savi_speed.synthetic_inputs(comp, (t.batch_size, t.clip_length, r, r, 3))
  step, state, batch, key = bc_speed.step_inputs(config.policy, config.savi.num_slots, config.savi.slot_size)
  return {"savi": _timed(comp.train_step, savi_args, steps), "policy": _timed(step, (state, batch, key), steps)}


def main() -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--variant", default="tiny", help="the config variant whose SAVi and policy are timed")
  parser.add_argument("--suite", action="store_true", help="the test suite's SAVi (tests/test_savi.py tiny_config)")
  parser.add_argument("--steps", type=int, default=10, help="timed steps of each train step, after one warm-up")
  parser.add_argument("--case", default=None, help=argparse.SUPPRESS)     # a child: one case, its JSON on stdout
  args = parser.parse_args()
  if args.case is not None:
    print(json.dumps(child(args.variant, args.suite, CASES[args.case][1], args.steps)))
    return 0
  results = {}
  for name, (flag, _) in CASES.items():
    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS=f"{flag} --xla_force_host_platform_device_count=1".strip())
    out = subprocess.run([sys.executable, os.path.abspath(__file__), f"--variant={args.variant}",
                          f"--steps={args.steps}", f"--case={name}"] + ["--suite"] * args.suite, env=env,
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
      print(f"xla_emitters: the case {name!r} failed:\n{out.stderr[-3000:]}", file=sys.stderr)
      return 1
    results[name] = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"measured: {name}", file=sys.stderr, flush=True)
  base = results["fusion emitters, default level"]
  savi = "the test suite's (tests/test_savi.py)" if args.suite else f"variant {args.variant}'s"
  policy = "tiny" if args.suite else args.variant
  print(f"SAVi: {savi}; policy: variant {policy}'s; {args.steps} timed steps each, one host device, "
        f"{os.cpu_count()} CPUs")
  print("| case | SAVi compile s | SAVi step ms | policy compile s | policy step ms |")
  print("| --- | --- | --- | --- | --- |")
  for name, row in results.items():
    cells = []
    for model in ("savi", "policy"):
      (compile_s, step_s), (base_compile, base_step) = row[model], base[model]
      cells += [f"{compile_s:.2f} ({compile_s / base_compile:.2f}x)", f"{step_s * 1e3:.1f} ({step_s / base_step:.2f}x)"]
    print(f"| {name} | " + " | ".join(cells) + " |")
  return 0


if __name__ == "__main__":
  sys.exit(main())
