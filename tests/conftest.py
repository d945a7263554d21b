"""Shared pytest set-up: the repository root on sys.path so `configs` and `roboshape` import from any cwd, and the
tiny fixtures several test modules share (a synthetic episode and dataset, a whole tiny run)."""
import contextlib
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
# XLA's compiled programs kept on disk for the suite (JAX's persistent compilation cache): many tests, and the
# launch.py processes they start, compile the same tiny programs, which then load instead of compiling again. It
# lives in pytest's own cache folder, so it is never committed and `rm -rf .pytest_cache` clears it; a
# JAX_COMPILATION_CACHE_DIR already set wins.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(ROOT, ".pytest_cache", "jax"))
# Every program is kept, not only those that took over a second to compile (JAX's default): the suite's programs
# are small, and most of its compile time is many sub-second compiles that other tests and processes repeat.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# XLA:CPU's older kernel emitters rather than its MLIR fusion emitters, for the suite and the processes it starts:
# they compile small programs such as the suite's faster, most of all at the cheap optimisation level
# (`cheap_compiles`), and a fresh clone's suite spends much of its time compiling (benchmarks/xla_emitters.py --suite
# measures both kinds side by side). launch.py keeps XLA's default. An XLA_FLAGS that already chooses wins.
if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()

import numpy as np  # pylint: disable=wrong-import-position
import pytest  # pylint: disable=wrong-import-position

# How `make test` shares the suite between its workers (pytest-xdist, --dist loadscope): each module runs on one
# worker, so its fixtures (a simulator pool, a trained SAVi) are built once. The modules start longest first, so the
# last to start is short and neither worker waits long for the other at the end; the others follow in collection
# order. A stale order only balances the workers less well.
LONGEST_FIRST = ("test_savi", "test_data", "test_sim", "test_policy", "test_notebook", "test_reliability",
                 "test_devices", "test_eval", "test_envs", "test_ae", "test_encoders", "test_baselines", "test_lanes",
                 "test_records", "test_objects")


def pytest_collection_modifyitems(items):
  rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
  module = lambda item: os.path.splitext(os.path.basename(item.nodeid.split("::")[0]))[0]
  items.sort(key=lambda item: rank.get(module(item), len(rank)))    # stable: each module's tests keep their order


@contextlib.contextmanager
def cheap_compiles():
  """XLA's cheap optimisation level while the block runs: for compile-bound tests, whose programs run briefly."""
  import jax  # pylint: disable=import-outside-toplevel
  flag = "jax_disable_most_optimizations"
  before = jax.config.read(flag)
  jax.config.update(flag, True)
  try:
    yield
  finally:
    jax.config.update(flag, before)


@pytest.fixture()
def cheap_xla():
  """A compile-bound test: `cheap_compiles` while it runs."""
  with cheap_compiles():
    yield


@pytest.fixture(scope="module")
def cheap_xla_module():
  """A compile-bound test module (pytestmark = pytest.mark.usefixtures("cheap_xla_module")): `cheap_compiles` while
  its tests run."""
  with cheap_compiles():
    yield


def _synthetic_episode(seed: int, task: str = "push", resolution: int = 16, num_actions: int = 0,
                       success: bool = True, level: str = "train", state: bool = False) -> dict:
  """A fake simulator episode (the dict roboshape.sim yields): a red square sliding over a grey table.

  Deterministic per seed; num_actions 0 picks 8-15 actions from the seed. image uint8 [T+1,H,W,3]; with `state`
  also a privileged state float32 [T+1, 65] (as the simulator workers return it).
  """
  rng = np.random.default_rng(seed)
  steps = num_actions or int(rng.integers(8, 16))
  size = max(2, resolution // 6)
  image = np.empty((steps + 1, resolution, resolution, 3), np.uint8)
  image[:] = (90, 90, 100)
  image[:, resolution // 2:] = (150, 130, 110)
  segmentation = np.zeros((steps + 1, resolution, resolution), np.uint8)
  segmentation[:, resolution // 2:] = 1
  x0, y0 = rng.integers(0, resolution - size, 2)
  for t in range(steps + 1):
    x = (x0 + t) % (resolution - size)
    image[t, y0:y0 + size, x:x + size] = (200, 30, 30)
    segmentation[t, y0:y0 + size, x:x + size] = 3
  episode = dict(task=task, level=level, seed=int(seed), success=bool(success), env_version="synthetic-1",
                 terminated=bool(success), image=image, segmentation=segmentation,
                 action=rng.uniform(-1, 1, (steps, 7)).astype(np.float32),
                 reward=rng.uniform(0, 1, steps).astype(np.float32))
  if state:
    from roboshape.envs import state as state_lib  # pylint: disable=import-outside-toplevel
    episode["state"] = rng.uniform(-1, 1, (steps + 1, state_lib.DIM)).astype(np.float32)
  return episode


@pytest.fixture(scope="session")
def synthetic_episode():
  """The function (seed, task="push", resolution=16, num_actions=0, success=True) -> a fake simulator episode."""
  return _synthetic_episode


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory):
  """Path of a tiny complete RoboShape dataset (task push, 16x16, 4 train + 2 val synthetic episodes)."""
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
  path = str(tmp_path_factory.mktemp("synthetic_data") / "roboshape_push" / "1.0.0")
  return rlds.write_dataset(path, {"train": [_synthetic_episode(s) for s in range(4)],
                                   "val": [_synthetic_episode(1_000_000 + s) for s in range(2)]})


@contextlib.contextmanager
def _once_per_run(tmp_path_factory, name: str):
  """For a session fixture that more than one module uses: yields (folder, built), where `folder` is the same for
  every pytest-xdist worker of this run and `built` whether another worker already built the fixture there (the
  modules may run on different workers: the first builds it while the others wait). Outside xdist: a fresh folder
  of this session, not built."""
  if not os.environ.get("PYTEST_XDIST_WORKER"):          # set in each pytest-xdist worker
    yield tmp_path_factory.mktemp(name), False
    return
  import fcntl  # pylint: disable=import-outside-toplevel
  root = tmp_path_factory.getbasetemp().parent        # the workers' base folders share this one
  folder, stamp = root / name, root / f"{name}.built"
  with open(root / f"{name}.lock", "w") as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    built = stamp.exists()
    folder.mkdir(exist_ok=True)
    yield folder, built
    stamp.touch()


@pytest.fixture(scope="session")
def tiny_run(synthetic_dataset, tmp_path_factory):
  """The workdir of a whole tiny push x savi run: configs/push_savi.py:tiny on `synthetic_dataset` (16x16), through
  the stages pretrain, cache, train_policy and evaluate (one 10-step rollout at level train in a real simulator
  worker, no videos); built once per test run. Compile-bound, so built at XLA's cheap optimisation level."""
  with _once_per_run(tmp_path_factory, "tiny_run") as (folder, built):
    workdir = str(folder / "push_savi")
    if not built:
      _build_tiny_run(synthetic_dataset, workdir)
  return workdir


def _build_tiny_run(synthetic_dataset: str, workdir: str) -> None:
  from configs import common  # pylint: disable=import-outside-toplevel
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  config = common.get_config("push", "savi", "tiny")
  config.env.resolution, config.env.max_episode_steps = 16, 10
  config.data.dir = os.path.dirname(os.path.dirname(synthetic_dataset))    # <dir>/roboshape_push/1.0.0
  config.stages = ("pretrain", "cache", "train_policy", "evaluate")
  config.eval.levels, config.eval.rollouts_per_seed, config.eval.videos_per_level = ("train",), 1, 0
  config.sim.num_workers = 1
  with cheap_compiles():
    stages.run(config, workdir)


def fill_disk_at_checkpoint(monkeypatch, step: int) -> None:
  """Makes the disk full for the save of checkpoint `step`: orbax's writes of that step's metadata files fail with
  ENOSPC in orbax's own threads, as on a real full disk (patched at orbax's lowest Python write; the arrays go
  through TensorStore's native code). Other steps are written as usual."""
  import errno  # pylint: disable=import-outside-toplevel
  from orbax.checkpoint._src.path import async_path  # pylint: disable=import-outside-toplevel
  real = async_path.write_text

  async def write_text(path, text):
    if f"{os.sep}{step}.orbax-checkpoint-tmp" in str(path):
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return await real(path, text)

  monkeypatch.setattr(async_path, "write_text", write_text)
