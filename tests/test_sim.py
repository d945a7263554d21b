"""The numpy bridge to the simulator (the dicts of roboshape/sim/__init__.py): input checks, collection, closed
loop, worker failures."""
import os
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from configs import common
from roboshape.errors import UserError
from roboshape.envs import ids
from roboshape.sim import EnvSpec, SimPool, SimWorkerError, check_seeds

RESOLUTION = 32
EPISODE_KEYS = {"task", "level", "seed", "success", "env_version", "terminated", "image", "segmentation", "state",
                "action", "reward"}


@pytest.fixture(scope="module")
def pool():
  with SimPool(EnvSpec("place", resolution=RESOLUTION), num_workers=2) as p:
    yield p


@pytest.fixture(scope="module")
def episodes(pool):
  return sorted(pool.collect([3, 4]), key=lambda e: e["seed"])


def test_bad_input_fails_in_the_parent_with_a_clear_message():
  with pytest.raises(UserError, match="unknown task 'stack'.*push, pick, place"):
    EnvSpec("stack")
  with pytest.raises(UserError, match="unknown level 'L4'"):
    EnvSpec("pick", level="L4")
  with pytest.raises(UserError, match="resolution"):
    EnvSpec("pick", resolution=4)
  with pytest.raises(UserError, match="min_distractors"):
    EnvSpec("pick", min_distractors=3, max_distractors=2)
  for bad in ([1.5], ["7"], [True], [-1], [2**31]):
    with pytest.raises(UserError, match="seed"):
      check_seeds(bad)
  assert check_seeds(np.arange(3)) == [0, 1, 2]


def test_spec_from_config():
  config = common.get_config("pick", "savi", "tiny")
  config.env.resolution = 48
  spec = EnvSpec.from_config(config, level="L2")
  assert spec == EnvSpec("pick", "L2", 48, 1, 4, 0, "physx_cpu")
  assert EnvSpec.from_config(config).level == "train"


def test_parent_does_not_import_the_simulator():
  code = "import sys, roboshape.sim; assert not {'sapien', 'mani_skill'} & set(sys.modules), 'simulator imported'"
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  subprocess.run([sys.executable, "-c", code], cwd=root, check=True, env=dict(os.environ, PYTHONPATH=root))


def test_collected_episodes_follow_the_contract(pool, episodes):
  assert [e["seed"] for e in episodes] == [3, 4]
  for e in episodes:
    assert set(e) == EPISODE_KEYS
    steps = len(e["action"])
    assert 0 < steps <= pool.horizon
    assert e["task"] == "place" and e["level"] == "train" and e["env_version"] == pool.env_version
    assert e["success"] and e["terminated"]  # the expert solves these seeds
    assert e["image"].dtype == np.uint8 and e["image"].shape == (steps + 1, RESOLUTION, RESOLUTION, 3)
    assert e["segmentation"].dtype == np.uint8 and e["segmentation"].shape == (steps + 1, RESOLUTION, RESOLUTION)
    assert e["state"].dtype == np.float32 and e["state"].shape == (steps + 1, 65)
    assert e["action"].dtype == np.float32 and e["action"].shape == (steps, 7)
    assert np.all(np.abs(e["action"]) <= 1.0)
    assert e["reward"].dtype == np.float32 and e["reward"].shape == (steps,) and e["reward"][-1] == 1.0
    assert {1, 2, 3, 4, ids.HAND} <= set(np.unique(e["segmentation"][0]).tolist())
    # The hand is its own object: it moves from where it starts to the bin, and FG-ARI's view merges it into the arm.
    first, last = (np.argwhere(s == ids.HAND).mean(0) for s in e["segmentation"][[0, -1]])
    assert np.abs(first - last).max() > 3
    assert ids.HAND not in ids.robot_as_one(e["segmentation"]) and ids.ROBOT in ids.robot_as_one(e["segmentation"])
    assert set(e["action"][:, 6].tolist()) == {-1.0, 1.0}  # the gripper closes and opens again


def test_closed_loop_replays_an_expert_episode_bit_for_bit(pool, episodes):
  e = episodes[0]
  obs = pool.reset([e["seed"], e["seed"]])
  frames = obs["image"]
  np.testing.assert_array_equal(obs["state"][0], e["state"][0])   # the state the dataset stores, from another worker
  assert frames.shape == (2, RESOLUTION, RESOLUTION, 3) and frames.dtype == np.uint8
  np.testing.assert_array_equal(frames[0], e["image"][0])  # same seed, another process: same first frame
  np.testing.assert_array_equal(frames[1], e["image"][0])
  steps = len(e["action"])
  for t in range(steps):
    out = pool.step(np.stack([e["action"][t], np.zeros(7, np.float32)]))
    assert out["elapsed"].tolist() == [t + 1, t + 1]
  assert out["success"].tolist() == [True, False] and out["done"].tolist() == [True, False]
  # Place's milestones: the expert's episode reached all (grasped, lifted, over the bin, in it), the still arm none.
  assert pool.milestones == ("grasped", "lifted", "over_bin", "in_bin")
  assert out["reached"].tolist() == [[True] * 4, [False] * 4]
  np.testing.assert_array_equal(out["image"][0], e["image"][-1])
  np.testing.assert_array_equal(out["segmentation"][0], e["segmentation"][-1])
  np.testing.assert_array_equal(out["state"][0], e["state"][-1])
  again = pool.step(np.ones((2, 7), np.float32))  # a done env ignores its action
  np.testing.assert_array_equal(again["image"][0], out["image"][0])
  assert again["elapsed"].tolist() == [steps, steps + 1] and again["done"][0]


def test_an_env_reset_without_render_has_the_same_state_and_no_frames(pool, episodes):
  e = episodes[0]
  obs = pool.reset([e["seed"], e["seed"]], render=[False, True])
  assert not obs["image"][0].any() and not obs["segmentation"][0].any()
  np.testing.assert_array_equal(obs["image"][1], e["image"][0])
  np.testing.assert_array_equal(obs["state"], e["state"][[0, 0]])
  for t in range(3):
    out = pool.step(np.stack([e["action"][t]] * 2))
  assert not out["image"][0].any()
  np.testing.assert_array_equal(out["image"][1], e["image"][3])
  np.testing.assert_array_equal(out["state"], e["state"][[3, 3]])   # the physics does not depend on the camera
  rendered = pool.reset([e["seed"]])                                  # the next reset renders again
  np.testing.assert_array_equal(rendered["image"][0], e["image"][0])


def test_closed_loop_input_checks(pool):
  with pytest.raises(UserError, match="seeds for a pool of 2"):
    pool.reset([1, 2, 3])
  with pytest.raises(UserError, match="one per seed"):
    pool.reset([1, 2], render=[True])
  pool.reset([1])
  with pytest.raises(UserError, match=r"shape \(1, 7\)"):
    pool.step(np.zeros((2, 7), np.float32))
  with pytest.raises(UserError, match="non-finite"):
    pool.step(np.full((1, 7), np.nan, np.float32))
  with pytest.raises(UserError, match="not an int"):
    list(pool.collect([0.5]))


def test_env_construction_error_comes_back_as_one_line(tmp_path, monkeypatch):
  monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))   # where the pool puts its workers' logs
  spec = EnvSpec("pick", resolution=RESOLUTION)
  object.__setattr__(spec, "task", "juggle")  # slips past the parent's check, fails inside the worker
  with pytest.raises(UserError) as info:
    SimPool(spec, num_workers=1)
  assert "unknown task 'juggle'" in str(info.value) and "\n" not in str(info.value)
  assert not os.listdir(tmp_path)   # the failed pool closed itself and removed its log folder


def test_a_dead_worker_raises_with_its_stderr_then_restart(pool):
  pool.reset([5, 6])
  pool._crash_worker(1, "boom-1234")  # pylint: disable=protected-access  (prints to stderr, exits with 3)
  with pytest.raises(SimWorkerError) as info:
    pool.step(np.zeros((2, 7), np.float32))
  message = str(info.value)
  assert "worker 1" in message and "code 3" in message and "boom-1234" in message, message  # its stderr
  assert "worker 0" not in message and "pool.restart()" in message, message
  with pytest.raises(SimWorkerError, match="worker 1"):
    pool.reset([5, 6])
  alive = pool._procs[0].popen.pid  # pylint: disable=protected-access
  pool.restart()  # replaces the dead worker only
  assert pool._procs[0].popen.pid == alive  # pylint: disable=protected-access
  frames = pool.reset([5, 6])["image"]
  assert frames.shape == (2, RESOLUTION, RESOLUTION, 3)


def test_worker_env_fixes_the_instruction_sets_unless_the_caller_sets_them():
  from roboshape.sim import pool as pool_lib  # pylint: disable=import-outside-toplevel
  env = pool_lib.worker_env({"PATH": "/bin", "ATEN_CPU_CAPABILITY": "default", "PYTHONPATH": "/elsewhere"})
  assert env["GALLIUM_OVERRIDE_CPU_CAPS"] == "avx" and env["OMP_NUM_THREADS"] == "1"
  assert env["ATEN_CPU_CAPABILITY"] == "default"   # the caller's value wins
  root = pool_lib._ROOT  # pylint: disable=protected-access
  assert env["PATH"] == "/bin" and env["PYTHONPATH"].split(os.pathsep) == [root, "/elsewhere"]


def test_a_worker_pinned_to_one_core_renders_the_frames_of_an_unpinned_one(pool, tmp_path):
  # A grid lane pins itself and its workers to one core (roboshape/lanes.py), where Mesa's renderer, left to pick
  # its instruction sets, crashed on one CPU family (roboshape/sim/pool.py WORKER_ENV).
  code = ("import os, sys, numpy as np; from roboshape.sim import EnvSpec, SimPool\n"
          "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n"
          f"with SimPool(EnvSpec('place', resolution={RESOLUTION}), num_workers=1) as p:\n"
          "  np.save(sys.argv[1], p.reset([5])['image'])\n")
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  free = pool.reset([5, 6])["image"][:1]   # the module's unpinned workers
  out = str(tmp_path / "frame.npy")
  temp = tmp_path / "temp"
  temp.mkdir()
  run = subprocess.run([sys.executable, "-c", code, out], cwd=root,
                       env=dict(os.environ, PYTHONPATH=root, TMPDIR=str(temp)), capture_output=True, text=True,
                       timeout=300)
  assert run.returncode == 0, run.stderr[-2000:]
  np.testing.assert_array_equal(np.load(out), free)
  assert not os.listdir(temp)   # the pool's log folder went with it
