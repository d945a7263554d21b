"""SimPool: N simulator worker processes behind a numpy API (the episode and frame dicts of roboshape/sim).

The parent never imports sapien or mani_skill: each worker is a fresh interpreter (`python -m
roboshape.sim.worker`), so whatever the parent imported (TensorFlow, JAX) stays out of it. A worker that dies is
reported as SimWorkerError with the tail of its stderr, within about a second; a worker that stops answering is
killed after a timeout. Both never hang the parent.

  with SimPool(EnvSpec("pick"), num_workers=2) as pool:
    for episode in pool.collect(range(10)):     # oracle demos, in completion order
      ...
    obs = pool.reset([0, 1])                    # closed loop: image uint8 [2, H, W, 3], segmentation, state, ...
    obs = pool.step(actions)                    # float32 [2, 7] -> the same keys after the step
"""
import collections
import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from multiprocessing.connection import Connection, wait
from typing import Dict, Iterable, Iterator, List, Optional, Sequence

import numpy as np

from roboshape import envs
from roboshape import fileio
from roboshape.errors import UserError
from roboshape.sim.spec import CAMERA_KEYS, EnvSpec, check_seeds

_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# The instruction sets a worker's libraries may pick, fixed rather than read off the CPU, so that an episode's bytes
# do not follow the machine it was collected on. Mesa's CPU renderer (llvmpipe, under lavapipe) compiles its shaders
# for the CPU's instruction sets, and frames rendered with SSE4.1-only code differ from those of AVX code; left to
# itself on AMD's family 1Ah CPUs (AVX-512) it also crashes a process pinned to one core, as a grid lane is.
# PyTorch, which ManiSkill's controllers run on, picks its kernels the same way, and its portable kernels give other
# states and actions than its AVX2 ones (AVX-512 gives the AVX2 bytes). AVX (llvmpipe) and AVX2 (PyTorch) are on every
# x86-64 server CPU of the last decade; elsewhere both variables are ignored. A value the caller's environment sets
# wins. OpenMP and MKL get one thread each: a worker is one env on one core. The measurements behind this:
# results/small/README.md, "Machines and speed".
WORKER_ENV = {"GALLIUM_OVERRIDE_CPU_CAPS": "avx", "ATEN_CPU_CAPABILITY": "avx2",
              "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def worker_env(parent: Optional[Dict[str, str]] = None) -> Dict[str, str]:
  """The environment a worker starts with: the parent's (default os.environ), this checkout on PYTHONPATH, and
  WORKER_ENV's values where the parent sets none."""
  env = dict(os.environ if parent is None else parent)
  env["PYTHONPATH"] = _ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
  for name, value in WORKER_ENV.items():
    env.setdefault(name, value)
  return env


class SimWorkerError(RuntimeError):
  """A simulator worker died, failed a command or stopped answering; the message holds its stderr tail."""


def _tail(path: str, max_lines: int = 15, max_chars: int = 2000) -> str:
  try:
    lines = [l for l in fileio.tail_lines(path) if "WARNING" not in l]
  except OSError:
    return "(no stderr)"
  return "\n".join(lines[-max_lines:])[-max_chars:] or "(empty stderr)"


class _Proc:
  """One worker process, its socket and its log file (stdout + stderr)."""

  def __init__(self, index: int, spec: EnvSpec, log_dir: str):
    self.index = index
    parent_sock, child_sock = socket.socketpair()
    self.log_path = os.path.join(log_dir, f"worker{index}.log")
    env = worker_env()
    with open(self.log_path, "wb") as log:
      self.popen = subprocess.Popen(
          [sys.executable, "-m", "roboshape.sim.worker", str(child_sock.fileno()),
           json.dumps(dataclasses.asdict(spec))],
          stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT, pass_fds=(child_sock.fileno(),),
          env=env, cwd=_ROOT)
    child_sock.close()
    self.conn = Connection(parent_sock.detach())
    self.info: Dict = {}

  def alive(self) -> bool:
    return self.popen.poll() is None

  def death_message(self, what: str) -> str:
    try:
      self.popen.wait(timeout=10)  # a dying simulator may take seconds to free its memory
    except subprocess.TimeoutExpired:
      pass
    code = self.popen.poll()
    status = "is still running" if code is None else f"exited with code {code}"
    return f"simulator worker {self.index} (pid {self.popen.pid}) {what}; it {status}. Its stderr ends with:\n" + \
        _tail(self.log_path)

  def kill(self) -> None:
    if self.alive():
      self.popen.kill()
      try:
        self.popen.wait(timeout=5)
      except subprocess.TimeoutExpired:
        pass
    self.conn.close()


def _stack(frames: List[dict]) -> Dict[str, np.ndarray]:
  """The workers' frame dicts stacked into arrays [N, ...] (every camera's frames: image, segmentation, depth where
  the spec asks for it, wrist_image, ...)."""
  views = {k: np.stack([o[k] for o in frames]) for k in CAMERA_KEYS if k in frames[0]}
  return dict(**views, reached=np.stack([o["reached"] for o in frames]).astype(bool),
              state=np.stack([o["state"] for o in frames]).astype(np.float32),
              success=np.array([o["success"] for o in frames], bool),
              done=np.array([o["done"] for o in frames], bool),
              elapsed=np.array([o["elapsed"] for o in frames], np.int32))


class SimPool:
  """N workers, each owning one RoboShape env of `spec` (the dicts they return: roboshape/sim/__init__.py).

  Args:
    spec: the env every worker builds.
    num_workers: number of worker processes (0: os.cpu_count()); pool.num_envs equals it.
    start_timeout: seconds a worker may take to build its env (its first picture also renders SAPIEN's BRDF
      lookup table, seconds on a CPU).
    step_timeout: seconds a worker may take for one reset / step.
    episode_timeout: seconds a worker may take for one expert episode in `collect`.
  """

  def __init__(self, spec: EnvSpec, num_workers: int = 0, start_timeout: float = 300.0,
               step_timeout: float = 120.0, episode_timeout: float = 600.0):
    if not isinstance(spec, EnvSpec):
      raise UserError(f"SimPool needs an EnvSpec, got {type(spec).__name__}")
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
      raise UserError(f"sim.num_workers must be an int >= 0 (0: one per CPU core), got {num_workers!r}")
    self.spec = spec
    self.milestones = envs.MILESTONES.get(spec.task, ())   # the names of the frame dicts' `reached` columns
    self.num_envs = num_workers or os.cpu_count() or 1
    self.start_timeout, self.step_timeout, self.episode_timeout = start_timeout, step_timeout, episode_timeout
    self._log_dir = tempfile.mkdtemp(prefix="roboshape_sim_")
    self._procs: List[Optional[_Proc]] = [None] * self.num_envs
    self._active = 0
    self.horizon = 0
    self.env_version = ""
    self.restart()

  # ------------------------------------------------------------------------------------------- lifecycle
  def restart(self) -> None:
    """Replaces every dead (or never started) worker with a fresh one and waits until they are ready."""
    fresh = []
    os.makedirs(self._log_dir, exist_ok=True)   # close() removed it
    for i, proc in enumerate(self._procs):
      if proc is None or not proc.alive():
        if proc is not None:
          proc.kill()
        self._procs[i] = _Proc(i, self.spec, self._log_dir)
        fresh.append(self._procs[i])
    deadline = time.time() + self.start_timeout
    try:
      for proc in fresh:
        proc.info = self._recv(proc, max(1.0, deadline - time.time()), "building its env")
    except (SimWorkerError, UserError):
      self.close()
      raise
    self.horizon = self._procs[0].info["horizon"]
    self.env_version = self._procs[0].info["env_version"]
    self._active = 0

  def close(self) -> None:
    """Asks every worker to exit, then kills what is left and removes the workers' log folder (the evaluation makes a
    pool per level, so a grid would otherwise leave hundreds of them in the temp folder)."""
    for proc in self._procs:
      if proc is not None and proc.alive():
        try:
          proc.conn.send(("close", None))
        except OSError:
          pass
    deadline = time.time() + 5
    for proc in self._procs:
      if proc is not None:
        try:
          proc.popen.wait(timeout=max(0.1, deadline - time.time()))
        except subprocess.TimeoutExpired:
          pass
        proc.kill()
    self._procs = [None] * self.num_envs
    shutil.rmtree(self._log_dir, ignore_errors=True)

  def __enter__(self) -> "SimPool":
    return self

  def __exit__(self, *exc) -> None:
    self.close()

  def __del__(self):
    try:
      self.close()
    except Exception:  # pylint: disable=broad-except
      pass

  # ------------------------------------------------------------------------------------------- messaging
  def _proc(self, i: int) -> _Proc:
    proc = self._procs[i]
    if proc is None:
      raise SimWorkerError("the pool is closed; create a new SimPool")
    return proc

  def _send(self, proc: _Proc, command: str, arg) -> None:
    try:
      proc.conn.send((command, arg))
    except OSError:
      raise SimWorkerError(proc.death_message(f"died before {command}")) from None

  def _recv(self, proc: _Proc, timeout: float, what: str):
    """The payload of the worker's next reply; SimWorkerError when it dies, fails or times out."""
    deadline = time.time() + timeout
    while True:
      if proc.conn.poll(min(0.5, max(0.0, deadline - time.time()))):
        try:
          status, payload = proc.conn.recv()
        except (EOFError, OSError):
          raise SimWorkerError(proc.death_message(f"died while {what}")) from None
        if status == "ok":
          return payload
        if what == "building its env":
          raise UserError(payload)
        raise SimWorkerError(f"simulator worker {proc.index} failed while {what}: {payload}")
      if not proc.alive():
        raise SimWorkerError(proc.death_message(f"died while {what}"))
      if time.time() >= deadline:
        proc.kill()
        raise SimWorkerError(proc.death_message(f"gave no answer in {timeout:.0f}s while {what} (killed)"))

  # ------------------------------------------------------------------------------------------- collection
  def collect(self, seeds: Iterable[int]) -> Iterator[dict]:
    """Runs the oracle expert from each seed; yields episode dicts (roboshape/sim/__init__.py) in completion order.

    Failed episodes (success False) are yielded too. A worker that dies raises SimWorkerError; after
    `restart()` the caller may collect the seeds it has not received yet.
    """
    pending = collections.deque(check_seeds(seeds))
    busy: Dict[int, int] = {}  # worker index -> seed
    self._active = 0

    def feed(i):
      if pending:
        seed = pending.popleft()
        self._send(self._proc(i), "collect", seed)
        busy[i] = seed

    for i in range(self.num_envs):
      feed(i)
    started = {i: time.time() for i in busy}
    try:
      while busy:
        conns = {self._proc(i).conn: i for i in busy}
        for conn in wait(list(conns), timeout=0.5):
          i = conns[conn]
          episode = self._recv(self._proc(i), 1.0, f"collecting seed {busy.pop(i)}")
          feed(i)
          started[i] = time.time()
          yield episode
        for i in list(busy):
          proc = self._proc(i)
          if not proc.alive() and not proc.conn.poll(0):
            raise SimWorkerError(proc.death_message(f"died while collecting seed {busy[i]}"))
          if time.time() - started[i] > self.episode_timeout:
            proc.kill()
            raise SimWorkerError(proc.death_message(
                f"gave no episode in {self.episode_timeout:.0f}s for seed {busy[i]} (killed)"))
    finally:
      if busy:  # the caller stopped early or a worker failed: drain the others so the pool stays usable
        for i in list(busy):
          proc = self._procs[i]
          if proc is not None and proc.alive():
            try:
              self._recv(proc, self.episode_timeout, f"collecting seed {busy[i]}")
            except (SimWorkerError, UserError):
              pass

  # ------------------------------------------------------------------------------------------- closed loop
  def reset(self, seeds: Sequence[int], render: Optional[Sequence[bool]] = None) -> Dict[str, np.ndarray]:
    """Resets env i from seeds[i] (len(seeds) <= num_envs); returns their first observations, as `step` does.

    render: per env, whether its camera is rendered this episode (default: all). An env reset with False returns
    zeros for image, segmentation and depth until its next reset, and its steps cost the physics alone.
    """
    seeds = check_seeds(seeds)
    if not 0 < len(seeds) <= self.num_envs:
      raise UserError(f"pool.reset got {len(seeds)} seeds for a pool of {self.num_envs} envs; "
                      f"pass between 1 and {self.num_envs}")
    render = [True] * len(seeds) if render is None else [bool(x) for x in render]
    if len(render) != len(seeds):
      raise UserError(f"pool.reset got {len(render)} render flags for {len(seeds)} seeds; pass one per seed")
    out = self._broadcast("reset", list(zip(seeds, render)))
    self._active = len(seeds)
    return _stack(out)

  def step(self, actions: np.ndarray) -> Dict[str, np.ndarray]:
    """Executes actions float32 [N, 7] (clipped to [-1, 1]) in the N envs of the last reset.

    Returns image uint8 [N, H, W, 3], segmentation uint8 [N, H, W], state float32 [N, envs.state.DIM] (the
    privileged state), depth uint16 [N, H, W] (mm, only with spec.depth), success bool [N], done bool [N]
    (success or horizon), elapsed int32 [N] and reached bool [N, M] (the task's milestones, `self.milestones`,
    reached since the reset). A done env ignores its action and returns its last observation.
    """
    if self._active == 0:
      raise UserError("pool.step before pool.reset: reset the envs with seeds first")
    actions = np.asarray(actions, np.float32)
    if actions.shape != (self._active, 7):
      raise UserError(f"pool.step needs actions of shape ({self._active}, 7), got {actions.shape}")
    if not np.all(np.isfinite(actions)):
      raise UserError("pool.step got non-finite actions (NaN or inf)")
    return _stack(self._broadcast("step", list(actions)))

  def _broadcast(self, command: str, args: list) -> List[dict]:
    procs = [self._proc(i) for i in range(len(args))]
    sent, errors = [], []
    for proc, arg in zip(procs, args):
      try:
        self._send(proc, command, arg)
        sent.append(proc)
      except SimWorkerError as e:
        errors.append(str(e))
    out = []
    for proc in sent:  # read every reply, so no answer is left behind for the next command
      try:
        out.append(self._recv(proc, self.step_timeout, command))
      except SimWorkerError as e:
        errors.append(str(e))
    if errors:
      raise SimWorkerError("\n".join(errors) + "\nCall pool.restart() to replace dead workers.")
    return out

  def _crash_worker(self, i: int, message: str = "test") -> None:
    """Test hook: makes worker i print `message` to stderr and exit with code 3, like a crashing simulator."""
    self._send(self._proc(i), "_crash", message)
