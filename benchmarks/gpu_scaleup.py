"""The `:paper` train steps on one GPU, and the GPU-hours of the `:paper` grid they imply.

Meant to run once on a lent GPU machine (one H100 or H200; JAX with its CUDA plugin; no TensorFlow, ManiSkill or SAPIEN;
ml_collections carried as a wheel in .whl/), from the repository root:

  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      .whl/*.whl && export PYTHONPATH=/tmp/site:$PYTHONPATH || exit; \
      PYTHONUNBUFFERED=1 python3 benchmarks/gpu_scaleup.py 2>&1 | tee $OUT/gpu_scaleup.txt

Without a GPU it prints one line and exits 0. On a GPU it measures, each as the median over rounds of chained steps
after compiling and one warm-up step (jax.block_until_ready at the end of each round):
  SAVi:  the `:paper` SAVi-S pretrain step (forward, backward, Adam) at pretrain.train.batch_size clips of
         pretrain.train.clip_length 64x64 frames, built as benchmarks/savi_speed.py builds it (pretrain.compiled);
  BC:    the `:paper` behaviour-cloning step (policy.width, num_layers, policy.train.batch_size, history) on SAVi-like
         tokens (savi.num_slots x savi.slot_size a frame), built as benchmarks/bc_speed.py builds it
         (bc_speed.compiled_step, the batch on the device as train_policy puts it);
  AE:    the `ae` encoder's pretrain step (pretrain.compiled, the same pretrain section as SAVi's); if it fails,
         the SAVi step stands in for it in the projection, as an upper bound (said in the output);
  matmul: a dense float32 matmul (benchmarks/flops.py) at JAX's default precision, the rate the steps are set against.
Each step's FLOPs come from XLA's cost analysis of the step lowered for the CPU, before a backend optimises it (on the
GPU, the compiled step's convolutions and matmuls are cuDNN and cuBLAS calls that the analysis counts as nothing:
flops.step_flops); achieved TFLOP/s = FLOPs / median step time.
Then it prints the GPU-hours of the `:paper` grid (configs/reproduce.py:paper, and every registered encoder) from
those step times and the configs' step counts and seeds, with the assumptions and what is left out, and one
"unmeasured: <reason>" line for each thing this machine cannot run (the `:tiny` pipeline, ManiSkill's physx_cuda),
or a try at it where its imports work.

  --smoke --allow-cpu: the `:tiny` variant, batch 2, one round of one step, on whatever device (a check of the
  script, not a measurement); --allow-cpu alone runs the full measurement on a CPU; --flops-only prints the three
  steps' FLOPs and nothing else, on any device, in under a minute (they do not depend on the device).
"""
import argparse
import dataclasses
import importlib.util
import os
import subprocess
import sys
import tempfile
import time

START = time.perf_counter()   # before the imports below, so the total wall time counts them
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
# Importing bc_speed makes JAX's CPU platform one device per core (roboshape/cli.py) unless XLA_FLAGS already sets
# the count: keep one CPU device (the GPU is unaffected; a --allow-cpu run then measures one device, as a GPU is).
_HOST_FLAG = "--xla_force_host_platform_device_count"
if _HOST_FLAG not in os.environ.get("XLA_FLAGS", ""):
  os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_HOST_FLAG}=1".strip()

import jax  # pylint: disable=wrong-import-position
import numpy as np  # pylint: disable=wrong-import-position

import bc_speed  # pylint: disable=wrong-import-position  (benchmarks/bc_speed.py)
import flops  # pylint: disable=wrong-import-position  (benchmarks/flops.py)
import savi_speed  # pylint: disable=wrong-import-position  (benchmarks/savi_speed.py)
from configs import common  # pylint: disable=wrong-import-position
from configs import reproduce  # pylint: disable=wrong-import-position
from roboshape import encoders  # pylint: disable=wrong-import-position
from roboshape import grid as grid_lib  # pylint: disable=wrong-import-position
from roboshape import rundir  # pylint: disable=wrong-import-position
from roboshape.models import savi  # pylint: disable=wrong-import-position
from roboshape.train import pretrain  # pylint: disable=wrong-import-position
from roboshape.train import sharding  # pylint: disable=wrong-import-position

SIM_MODULES = ("mani_skill", "sapien")                         # the simulator
DATA_MODULES = ("tensorflow", "tensorflow_datasets")           # the RLDS/TFDS dataset and the feature cache
HEAVY_MODULES = SIM_MODULES + DATA_MODULES + ("torch",)
TRY_MIN_S = 60           # seconds of budget a try at the :tiny pipeline or physx_cuda needs left to start


def log(message: str) -> None:
  print(f"[gpu_scaleup +{time.perf_counter() - START:6.1f} s] {message}", flush=True)


def elapsed() -> float:
  return time.perf_counter() - START


@dataclasses.dataclass
class Measured:
  """One timed step: median seconds a step, the per-round values, FLOPs a step, compile seconds, parameters."""
  name: str
  step_s: float
  rounds: list
  flops: float
  compile_s: float
  params: int

  def line(self) -> str:
    return (f"{self.name}: {1e3 * self.step_s:.2f} ms/step median (rounds: "
            f"{', '.join(f'{1e3 * t:.2f}' for t in self.rounds)} ms); {self.flops / 1e9:.1f} GFLOP/step -> "
            f"{self.flops / self.step_s / 1e12:.2f} TFLOP/s; compile {self.compile_s:.1f} s; "
            f"{self.params:,} parameters")


def parameter_count(params) -> int:
  return int(sum(np.prod(leaf.shape) for leaf in jax.tree_util.tree_leaves(params)))


def time_rounds(step, state, args, rounds: int, steps: int) -> list:
  """Seconds a step of `steps` chained calls `state, metrics = step(state, *args)`, for each of `rounds` rounds."""
  state, metrics = step(state, *args)            # warm-up
  jax.block_until_ready((state, metrics))
  times = []
  for _ in range(rounds):
    start = time.perf_counter()
    for _ in range(steps):
      state, metrics = step(state, *args)
    jax.block_until_ready((state, metrics))
    times.append((time.perf_counter() - start) / steps)
  return times


def reconstruction_inputs(comp, config):
  """(state, video, depth, first, key, pixel_weight) of a pretrain step: savi_speed.synthetic_inputs at the config's
  batch and clips."""
  t, res = config.pretrain.train, int(config.env.resolution)
  return savi_speed.synthetic_inputs(comp, (int(t.batch_size), int(t.clip_length), res, res, 3))


def measure_reconstruction(name: str, comp, config, rounds: int, steps: int) -> Measured:
  """A pretrain step (pretrain.Compiled: SAVi's or the AE's) on random uint8 clips of the config's batch and clip
  length, state and batch placed as benchmarks/savi_speed.py and the pretrain stage place them."""
  state, *inputs = reconstruction_inputs(comp, config)
  step_flops = flops.step_flops(comp.train_step, state, *inputs)   # first: it fails in seconds, if at all
  start = time.perf_counter()
  compiled = comp.train_step.lower(state, *inputs).compile()
  compile_s = time.perf_counter() - start
  times = time_rounds(compiled, state, tuple(inputs), rounds, steps)
  return Measured(name, float(np.median(times)), times, step_flops, compile_s, parameter_count(state["params"]))


def paper_config(encoder: str, variant: str, batch: int):
  config = common.get_config("pick", encoder, variant)
  config.env.resolution = 64
  if batch:
    config.pretrain.train.batch_size = batch
  return config


def measure_savi(variant: str, batch: int, rounds: int, steps: int) -> Measured:
  config = paper_config("savi", variant, batch)
  pretrain.validate_config(config)
  t = config.pretrain.train
  log(f"SAVi ({variant}): batch {t.batch_size} x {t.clip_length} frames of 64x64, K={config.savi.num_slots}, "
      f"D={config.savi.slot_size}; compiling")
  return measure_reconstruction("SAVi pretrain step", pretrain.compiled(config), config, rounds, steps)


def measure_ae(variant: str, batch: int, rounds: int, steps: int) -> Measured:
  config = paper_config("ae", variant, batch)
  pretrain.validate_config(config)
  log("AE: the same batch and clips as SAVi's; compiling")
  return measure_reconstruction("AE pretrain step", pretrain.compiled(config), config, rounds, steps)


def bc_config(variant: str, batch: int):
  """The policy section of the timed BC step, and the SAVi-like tokens it reads (slots x slot size a frame)."""
  config = common.get_config("push", "savi", variant)
  pc = config.policy
  if batch:
    pc.train.batch_size = batch
  return pc, int(config.savi.num_slots), int(config.savi.slot_size)


def measure_bc(variant: str, batch: int, rounds: int, steps: int) -> Measured:
  """bc_speed.compiled_step on SAVi-like tokens, with the state and batch on the device (sharding.DataParallel,
  as train_policy places them), so the timed step moves no batch from the host."""
  pc, tokens, dim = bc_config(variant, batch)
  log(f"BC ({variant}): width {pc.width}, {pc.num_layers} layers, {pc.num_heads} heads, batch "
      f"{pc.train.batch_size}, history {pc.history}, {tokens} tokens x {dim} a frame; compiling")
  start = time.perf_counter()
  compiled, step_flops, state, data, key = bc_speed.compiled_step(pc, tokens, dim, sharding.DataParallel(
      pc.train.batch_size))
  compile_s = time.perf_counter() - start
  times = time_rounds(compiled, state, (data, key), rounds, steps)
  return Measured("BC train step", float(np.median(times)), times, step_flops, compile_s,
                  parameter_count(state["params"]))


def count_flops(variant: str, batch: int) -> None:
  """Each timed step's FLOPs (flops.step_flops) without compiling or timing it: under a minute on any device."""
  for encoder, name in (("savi", "SAVi pretrain step"), ("ae", "AE pretrain step")):
    config = paper_config(encoder, variant, batch)
    comp = pretrain.compiled(config)
    log(f"{name}: {flops.step_flops(comp.train_step, *reconstruction_inputs(comp, config)) / 1e9:.1f} GFLOP/step")
  pc, tokens, dim = bc_config(variant, batch)
  step, *inputs = bc_speed.step_inputs(pc, tokens, dim)
  log(f"BC train step: {flops.step_flops(step, *inputs) / 1e9:.1f} GFLOP/step")


def attempt(label: str, measure, *args):
  """measure(*args), logged; None (and one line) on failure."""
  try:
    result = measure(*args)
  except Exception as error:  # pylint: disable=broad-except
    log(f"{label} FAILED: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}")
    return None
  log(result.line())
  log(f"device memory peak so far: {peak_memory()}")
  return result


def peak_memory() -> str:
  stats = jax.devices()[0].memory_stats() or {}
  peak = stats.get("peak_bytes_in_use")
  return f"{peak / 2**30:.1f} GiB" if peak is not None else "not reported by this backend"


def tokens_per_frame(config, encoder: str) -> str:
  """What one frame becomes for the policy: 'N x D' where its encoder says so without being built (its Kind)."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  return encoders.tokens_per_frame(config, encoder)


@dataclasses.dataclass
class Row:
  """One encoder's share of the grid over its tasks: runs and steps of pretraining and of behaviour cloning."""
  encoder: str
  tasks: int = 0
  pretrain_runs: int = 0
  pretrain_steps: int = 0
  pretrain_s: float = 0.0
  bc_runs: int = 0
  bc_steps: int = 0
  bc_s: float = 0.0
  tokens: str = ""
  in_paper_grid: bool = False


def grid_rows(pretrain_step_s: dict, bc_step_s: float) -> list:
  """A Row per registered encoder over the `:paper` grid's tasks, its runs and seeds as grid.grid_configs makes them
  (configs/reproduce.py:paper with grid.encoders set to every registered encoder)."""
  config = reproduce.get_config("paper")
  paper_encoders = tuple(config.grid.encoders)
  config.grid.encoders = encoders.names()
  rows = {}
  for _, encoder, sub, _ in grid_lib.grid_configs(config, tempfile.gettempdir()):
    row = rows.setdefault(encoder, Row(encoder, tokens=tokens_per_frame(sub, encoder),
                                       in_paper_grid=encoder in paper_encoders))
    row.tasks += 1
    if encoders.get(encoder).pretrain:
      runs = len(rundir.train_seeds(sub, "pretrain"))
      row.pretrain_runs += runs
      row.pretrain_steps = int(sub.pretrain.train.steps)
      row.pretrain_s += runs * int(sub.pretrain.train.steps) * pretrain_step_s.get(encoder, pretrain_step_s["savi"])
    runs = len(rundir.train_seeds(sub))
    row.bc_runs += runs
    row.bc_steps = int(sub.policy.train.steps)
    row.bc_s += runs * int(sub.policy.train.steps) * bc_step_s
  return list(rows.values())


def print_projection(savi_m: Measured, ae_m, bc_m: Measured, smoke: bool) -> None:
  ae_s = ae_m.step_s if ae_m else savi_m.step_s
  rows = grid_rows({"savi": savi_m.step_s, "ae": ae_s}, bc_m.step_s)
  print(flush=True)
  print("Projected GPU-hours of the :paper grid on this GPU (one run at a time, as grid.lanes=1 runs it):", flush=True)
  if smoke:
    print("  SMOKE RUN: the step times below are the :tiny model's, so these hours mean nothing.", flush=True)
  ae_note = ("measured" if ae_m else "NOT measured: the SAVi step time stands in (an upper bound: the AE shares "
             "SAVi's CNN encoder and decoder but decodes once a frame, not once per slot)")
  print(f"  step times: SAVi {savi_m.step_s * 1e3:.2f} ms, AE {ae_s * 1e3:.2f} ms ({ae_note}), BC "
        f"{bc_m.step_s * 1e3:.2f} ms", flush=True)
  for r in rows:
    pre = (f"pretrain {r.pretrain_runs} runs x {r.pretrain_steps:,} steps = {r.pretrain_s / 3600:7.2f} h"
           if r.pretrain_runs else f"pretrain {'-':>30}")
    print(f"  {r.encoder:<8} x{r.tasks} tasks{' (reproduce.py:paper grid)' if r.in_paper_grid else '':<27} {pre}; "
          f"BC {r.bc_runs} runs x {r.bc_steps:,} steps = {r.bc_s / 3600:6.2f} h; tokens a frame {r.tokens}",
          flush=True)
  paper = [r for r in rows if r.in_paper_grid]
  for label, subset in ((f"configs/reproduce.py:paper grid ({', '.join(r.encoder for r in paper)})", paper),
                        (f"every registered encoder ({', '.join(r.encoder for r in rows)})", rows)):
    pre, bc = sum(r.pretrain_s for r in subset), sum(r.bc_s for r in subset)
    print(f"  total, {label}: pretrain {pre / 3600:.1f} h + BC {bc / 3600:.1f} h = {(pre + bc) / 3600:.1f} "
          f"GPU-hours", flush=True)
  print_assumptions(savi_m, ae_m, bc_m)


def print_assumptions(savi_m: Measured, ae_m, bc_m: Measured) -> None:
  ev = common.get_config("push", "savi", "paper").eval
  lines = (
      "hours = runs x steps (the :paper configs' pretrain.train.steps, policy.train.steps) x the median step time "
      "above; runs: pretraining seeds (pretrain.train_seeds, () = one run) and policy training seeds "
      "(reproduce.py's grid.train_seeds per task) per cell of 3 tasks x encoder",
      f"each run also compiles its step once (SAVi {savi_m.compile_s:.0f} s, "
      f"{f'AE {ae_m.compile_s:.0f} s, ' if ae_m else ''}BC {bc_m.compile_s:.0f} s here), not counted",
      "the timed steps reuse one batch already on the GPU: the input pipeline (TFDS clips for pretraining, the "
      "feature cache's windows for BC), checkpoints, logging and in-training validation (SAVi every "
      "pretrain.eval.every steps, BC every policy.train.eval_every) are not counted",
      "BC of every encoder is timed on SAVi's tokens (the most a frame of the paper's encoders gives the trunk: "
      "its sequence is history x (tokens + 1)); fewer tokens a frame cost at most that, so those BC hours are "
      "upper bounds",
      "XLA's cost analysis counts a loop's body once: SAVi's slot processor is scanned over the clip's frames, so "
      "its FLOPs (the corrector and predictor, small beside the CNNs) are undercounted and TFLOP/s is a lower bound",
      "NOT included: data collection (expert demos in the simulator: mani_skill + SAPIEN), writing and reading the "
      "RLDS/TFDS dataset and the cache stage that encodes it (TensorFlow), closed-loop evaluation (the simulator: "
      f"{ev.num_seeds} seeds x {ev.rollouts_per_seed} rollouts x {len(ev.levels)} levels per policy), "
      "R3M/DINO feature extraction (reads the TFDS dataset with "
      "the official torch checkpoints): the simulator and TensorFlow are absent on this machine",
  )
  print("  assumptions:", flush=True)
  for line in lines:
    print(f"    - {line}", flush=True)


def missing(modules) -> list:
  return [m for m in modules if importlib.util.find_spec(m) is None]


def not_tried(smoke: bool) -> str:
  return "a smoke run tries nothing" if smoke else "too little of the time budget is left"


def try_tiny_pipeline(budget_s: float, smoke: bool) -> None:
  """`make demo`'s pipeline (configs/reproduce.py:tiny) in a temporary workdir, where its imports work."""
  absent = missing(SIM_MODULES + DATA_MODULES)
  label = "the :tiny pipeline (configs/reproduce.py:tiny: collect, pretrain, cache, train_policy, evaluate)"
  if absent:
    log(f"unmeasured: {label}: needs TensorFlow + TFDS (the dataset) and mani_skill + SAPIEN (the simulator); "
        f"not importable here: {', '.join(absent)}")
    return
  left = budget_s - elapsed() - 30
  if smoke or left < TRY_MIN_S:
    log(f"unmeasured: {label}: its imports work, but {not_tried(smoke)}")
    return
  with tempfile.TemporaryDirectory() as workdir:
    start = time.perf_counter()
    try:
      done = subprocess.run([sys.executable, os.path.join(ROOT, "launch.py"), "--config=configs/reproduce.py:tiny",
                             f"--workdir={workdir}"], cwd=ROOT, capture_output=True, text=True, timeout=left,
                            check=False)
      tail = (done.stdout + done.stderr).strip().splitlines()[-1:] or [""]
      log(f"{label}: exit {done.returncode} in {time.perf_counter() - start:.1f} s; last line: {tail[0][:200]}")
    except Exception as error:  # pylint: disable=broad-except
      log(f"{label} FAILED after {time.perf_counter() - start:.1f} s: {type(error).__name__}: {error}")


def try_physx_cuda(budget_s: float, smoke: bool, steps: int = 50) -> None:
  """Env steps/s of one RoboShape env on ManiSkill's GPU physics (env.sim_backend="physx_cuda"), where it imports."""
  absent = missing(SIM_MODULES + ("torch",))
  label = "ManiSkill physx_cuda (env.sim_backend='physx_cuda') env steps/s"
  if absent:
    log(f"unmeasured: {label}: needs mani_skill + SAPIEN (+ torch), and SAPIEN's GPU PhysX library "
        f"(libPhysXGpu_64.so, which SAPIEN downloads from GitHub at first use); not importable here: {', '.join(absent)}")
    return
  if smoke or budget_s - elapsed() < TRY_MIN_S:
    log(f"unmeasured: {label}: its imports work, but {not_tried(smoke)}")
    return
  try:
    import torch  # pylint: disable=import-outside-toplevel
    from roboshape import envs  # pylint: disable=import-outside-toplevel
    env = envs.make_env("push", "train", resolution=64, obs_mode="rgb+segmentation", sim_backend="physx_cuda")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = [torch.as_tensor(rng.uniform(-1, 1, (1, 7)), dtype=torch.float32) for _ in range(steps + 5)]
    for action in actions[:5]:
      env.step(action)
    start = time.perf_counter()
    for action in actions[5:]:
      env.step(action)
    step_s = (time.perf_counter() - start) / steps
    env.close()
    log(f"{label}: push, one env, 64x64 rgb+segmentation, random actions: {1 / step_s:.1f} steps/s")
  except Exception as error:  # pylint: disable=broad-except
    log(f"{label} FAILED: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}")


def parse_args():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--allow-cpu", action="store_true", help="measure even when JAX has no GPU")
  parser.add_argument("--smoke", action="store_true", help="the :tiny variant, batch 2, one round of one step")
  parser.add_argument("--rounds", type=int, default=5)
  parser.add_argument("--savi-steps", type=int, default=3, help="chained SAVi (and AE) steps a round")
  parser.add_argument("--bc-steps", type=int, default=10, help="chained BC steps a round")
  parser.add_argument("--matmul", type=int, default=8192, help="side of the reference float32 matmul")
  parser.add_argument("--flops-only", action="store_true",
                      help="print each step's FLOPs and exit: no compiling or timing, so under a minute on a CPU too")
  parser.add_argument("--budget-s", type=float, default=420.0,
                      help="seconds after which the tries (the :tiny pipeline, physx_cuda) are not started")
  args = parser.parse_args()
  if args.smoke:
    args.rounds, args.savi_steps, args.bc_steps, args.matmul = 1, 1, 1, 256
  return args


def header(variant: str) -> None:
  import flax  # pylint: disable=import-outside-toplevel
  import optax  # pylint: disable=import-outside-toplevel
  device = jax.devices()[0]
  heavy = [m for m in HEAVY_MODULES if m in sys.modules]
  log(f"device: {device.device_kind} x{jax.device_count()} ({jax.default_backend()}); jax {jax.__version__}, flax "
      f"{flax.__version__}, optax {optax.__version__}; variant {variant}; simulator/TF/torch modules imported: "
      f"{', '.join(heavy) or 'none'}")
  if variant == "paper":
    count = savi.parameter_count(paper_config("savi", "paper", 0).savi, 64)
    log(f"SAVi-S parameters (savi.parameter_count): {count:,}")


def print_matmul(side: int, measured) -> None:
  """The reference dense float32 matmul's rate and each measured step's share of it."""
  try:
    rate = flops.matmul_flops_per_s(n=side, reps=5)
  except Exception as error:  # pylint: disable=broad-except
    log(f"matmul reference FAILED: {type(error).__name__}: {error}")
    return
  shares = ", ".join(f"{m.name} {m.flops / m.step_s / rate:.3f}" for m in measured if m) or "nothing measured"
  log(f"dense float32 matmul {side}^3 at JAX's default precision: {rate / 1e12:.2f} TFLOP/s; share of it: {shares}")


def main() -> int:
  args = parse_args()
  variant, batch = ("tiny", 2) if args.smoke else ("paper", 0)
  if args.flops_only:
    header(variant)
    count_flops(variant, batch)
    return 0
  if jax.default_backend() != "gpu" and not args.allow_cpu:
    print(f"gpu_scaleup: no GPU found (jax {jax.__version__} backend {jax.default_backend()!r}): the README's GPU "
          "figures stay unmeasured.", flush=True)
    return 0
  header(variant)
  savi_m = attempt("SAVi pretrain step", measure_savi, variant, batch, args.rounds, args.savi_steps)
  ae_m = attempt("AE pretrain step", measure_ae, variant, batch, args.rounds, args.savi_steps)
  bc_m = attempt("BC train step", measure_bc, variant, batch, args.rounds, args.bc_steps)
  print_matmul(args.matmul, (savi_m, ae_m, bc_m))
  if savi_m and bc_m:
    print_projection(savi_m, ae_m, bc_m, args.smoke)
  else:
    log("no projection: the SAVi and BC steps must both be measured")
  try_tiny_pipeline(args.budget_s, args.smoke)
  try_physx_cuda(args.budget_s, args.smoke)
  log(f"total wall time {elapsed():.1f} s")
  return 0 if savi_m and bc_m else 1


if __name__ == "__main__":
  sys.exit(main())
