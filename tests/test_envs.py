"""The RoboShape world: palettes per level, determinism, success detection, expert success.

SAPIEN must never share a process with TensorFlow (which other test modules import), so everything that touches the
simulator runs once in a child python process (`_child`, started by the module fixture) that pickles plain numpy
facts back; the tests below assert on them.
"""
import os
import pickle
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from roboshape import envs
from roboshape.envs import ids as seg_ids
from roboshape.envs import palettes

RESOLUTION = 64
FRAME_SEEDS = (0, 1, 2, 3)
EXPERT_SEEDS = (11, 12)


def _child(out_path: str) -> None:
  """Runs in a fresh process: renders frames, scripts states, runs the experts; pickles the facts."""
  import torch  # pylint: disable=import-outside-toplevel
  from mani_skill.utils.structs.pose import Pose  # pylint: disable=import-outside-toplevel
  from roboshape.envs import experts  # pylint: disable=import-outside-toplevel
  torch.set_num_threads(1)
  facts = {"frames": {}, "success": {}, "expert": {}}
  for level in palettes.LEVEL_NAMES:
    env = envs.make_env("place", level, resolution=RESOLUTION)
    task = env.unwrapped
    for seed in FRAME_SEEDS:
      obs, _ = env.reset(seed=seed)
      rgb, seg = task.frames(obs)
      draw = task.draws[0]
      facts["frames"][(level, seed)] = dict(rgb=rgb[0], seg=seg[0], background=draw.background,
                                            colors=draw.colors, sizes=draw.sizes, shapes=draw.shapes,
                                            table=draw.table,
                                            cube=task.privileged_state()["cube_p"][0].numpy())
    if level == "train":  # the same seed again, after other seeds: the same first frame, bit for bit
      obs, _ = env.reset(seed=FRAME_SEEDS[0])
      facts["again"] = task.frames(obs)[0][0]
    env.close()

  def place_cube(task, p):
    task.cube.set_pose(Pose.create_from_pq(torch.tensor([p], dtype=torch.float32)))
    return bool(task.evaluate()["success"][0])

  for name in envs.TASKS:
    env = envs.make_env(name, "train", obs_mode="state")
    task = env.unwrapped
    env.reset(seed=5)
    goal = task.goal_pos[0].numpy().astype(float)
    half = 0.02
    if name == "push":
      cases = {"on_target": [goal[0] + 0.02, goal[1] - 0.01, half], "off_target": [goal[0] + 0.08, goal[1], half]}
    elif name == "pick":  # at the goal but not held: not a success; held is checked by the expert test
      cases = {"at_goal_not_grasped": list(goal), "on_table": [goal[0], goal[1], half]}
    else:
      floor = task.FLOOR_TOP + half
      cases = {"in_bin": [goal[0] + 0.01, goal[1] - 0.01, goal[2] + floor],
               "above_bin": [goal[0], goal[1], goal[2] + 0.2], "beside_bin": [goal[0] + 0.1, goal[1], half]}
    facts["success"][name] = {case: place_cube(task, p) for case, p in cases.items()}
    expert = experts.make_expert(name, 1)
    results, seen = [], []
    milestones = []    # (milestones holding at reset, milestones reached at some step) per expert episode
    for seed in EXPERT_SEEDS:
      env.reset(seed=seed)
      expert.reset()
      start = task.cube.pose.p.clone()
      at_reset = task.milestones(start, task.evaluate())[0].numpy()
      reached = np.zeros_like(at_reset)
      ok = False
      for _ in range(task.HORIZON):
        state = task.privileged_state()
        action = expert.act(state)
        seen.append(({k: v.clone() for k, v in state.items()}, action.clone()))
        assert torch.all(action.abs() <= 1.0)
        _, _, _, _, info = env.step(action)
        reached |= task.milestones(start, info)[0].numpy()
        if bool(info["success"][0]):
          ok = True
          break
      results.append(ok)
      milestones.append((at_reset.tolist(), reached.tolist()))
    facts["expert"][name] = results
    facts.setdefault("milestones", {})[name] = milestones
    # Memoryless: a fresh expert shown the same states in reverse order repeats every action of the episodes.
    fresh = experts.make_expert(name, 1)
    facts.setdefault("memoryless", {})[name] = max(
        float((fresh.act(state) - action).abs().max()) for state, action in reversed(seen))
    # Batched over envs: one expert for two stacked states acts as two single-env experts do.
    states = []
    for seed in EXPERT_SEEDS:
      env.reset(seed=seed)
      states.append(task.privileged_state())
    k = max(s["obstacles"].shape[1] for s in states)
    for s in states:  # pad the distractor rows to a common count, as a batched env does
      pad = torch.tensor([[[10.0, 10.0, 0.0, 0.0]]]).repeat(1, k - s["obstacles"].shape[1], 1)
      s["obstacles"] = torch.cat([s["obstacles"], pad], 1)
    stacked = {key: torch.cat([s[key] for s in states]) for key in states[0]}
    single = torch.cat([experts.make_expert(name, 1).act(s) for s in states])
    facts["batched"] = facts.get("batched", {})
    facts["batched"][name] = (experts.make_expert(name, 2).act(stacked).numpy(), single.numpy())
    env.close()
  with open(out_path, "wb") as f:
    pickle.dump(facts, f)


@pytest.fixture(scope="module")
def facts():
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  with tempfile.TemporaryDirectory() as tmp:
    out = os.path.join(tmp, "facts.pkl")
    code = ("import importlib.util, sys; spec = importlib.util.spec_from_file_location('t', sys.argv[1]); "
            "m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); m._child(sys.argv[2])")
    env = dict(os.environ, PYTHONPATH=root, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", code, os.path.abspath(__file__), out], cwd=root, env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(out, "rb") as f:
      return pickle.load(f)


def _nearest_color(pixels: np.ndarray, candidates) -> tuple:
  """The candidate RGB that explains `pixels` [P, 3] best up to a brightness factor (shading) in [0.5, 1.2]."""
  p = np.median(pixels.astype(float), 0)
  best, best_err = None, np.inf
  for c in candidates:
    c = np.asarray(c, float)
    s = np.clip(p @ c / max(c @ c, 1e-6), 0.5, 1.2)
    err = np.linalg.norm(p - s * c)
    if err < best_err:
      best, best_err = tuple(int(v) for v in c), err
  return best


def test_check_args_rejects_bad_input():
  with pytest.raises(ValueError, match="unknown task"):
    envs.check_args("stack", "train")
  with pytest.raises(ValueError, match="unknown level"):
    envs.check_args("pick", "L4")
  with pytest.raises(ValueError, match="resolution"):
    envs.check_args("pick", "train", 8)
  with pytest.raises(ValueError, match="resolution"):
    envs.check_args("pick", "train", 64.0)


def test_level_palettes_are_the_papers():
  assert palettes.LEVELS["train"].distractor_colors["purple"] == (246, 0, 220)
  assert palettes.LEVELS["L1"].distractor_colors["dark_blue"] == (0, 28, 90)
  assert palettes.LEVELS["L2"].backgrounds["cyan"] == (39, 245, 245)
  assert set(palettes.LEVELS["L2"].distractor_colors.values()) == set(palettes.TRAIN_DISTRACTOR_COLORS.values())
  assert not set(palettes.L1_DISTRACTOR_COLORS.values()) & set(palettes.TRAIN_DISTRACTOR_COLORS.values())
  assert not set(palettes.L2_BACKGROUNDS.values()) & set(palettes.TRAIN_BACKGROUNDS.values())
  rng = np.random.default_rng(0)
  lo, hi = palettes.TRAIN_SIZE_RANGE
  l3 = [palettes.LEVELS["L3"].sample_size(rng) for _ in range(200)]
  assert all(s < lo or s > hi for s in l3) and min(l3) < lo and max(l3) > hi


@pytest.mark.parametrize("level", palettes.LEVEL_NAMES)
def test_distractor_pixels_fall_in_the_levels_palette(facts, level):
  palette = set(palettes.LEVELS[level].distractor_colors.values())
  everything = set(palettes.TRAIN_DISTRACTOR_COLORS.values()) | set(palettes.L1_DISTRACTOR_COLORS.values())
  checked = 0
  for seed in FRAME_SEEDS:
    frame = facts["frames"][(level, seed)]
    assert set(frame["colors"]) <= palette
    for j, color in enumerate(frame["colors"]):
      pixels = frame["rgb"][frame["seg"] == 5 + j]
      if len(pixels) < 6:  # tiny (L3) or hidden behind the arm
        continue
      assert _nearest_color(pixels, everything) == color, (level, seed, j)
      checked += 1
  assert checked >= 4


@pytest.mark.parametrize("level", palettes.LEVEL_NAMES)
def test_background_behind_the_table_is_the_levels_color(facts, level):
  for seed in FRAME_SEEDS:
    frame = facts["frames"][(level, seed)]
    assert frame["background"] in palettes.LEVELS[level].backgrounds.values()
    pixels = frame["rgb"][frame["seg"] == 0].astype(int)
    assert len(pixels) > 0.05 * RESOLUTION**2  # the backdrop shows behind the table
    rendered = np.median(pixels, 0)
    np.testing.assert_allclose(rendered, frame["background"], atol=6)
    if level == "L2":  # an unseen background: far from every training background
      assert min(np.abs(rendered - c).max() for c in palettes.TRAIN_BACKGROUNDS.values()) > 40


def test_l3_sizes_are_outside_the_training_range(facts):
  lo, hi = palettes.TRAIN_SIZE_RANGE
  for seed in FRAME_SEEDS:
    assert all(lo <= s <= hi for s in facts["frames"][("train", seed)]["sizes"])
    assert all(s < lo or s > hi for s in facts["frames"][("L3", seed)]["sizes"])


def test_scene_contents_and_segmentation(facts):
  shapes, tables, counts = set(), set(), set()
  for seed in FRAME_SEEDS:
    frame = facts["frames"][("train", seed)]
    seg, rgb = frame["seg"], frame["rgb"]
    ids = set(np.unique(seg).tolist())
    assert {0, 1, 2, 3, 4} <= ids
    assert ids - {0, 1, 2, 3, 4, seg_ids.HAND} <= {5 + j for j in range(len(frame["colors"]))}
    cube = rgb[seg == 3].astype(int)  # the red cube is red
    assert len(cube) >= 6 and np.all(np.median(cube, 0) > [120, -1, -1]) and np.median(cube[:, 1]) < 60
    shapes.update(frame["shapes"])
    tables.add(frame["table"])
    counts.add(len(frame["colors"]))
  assert counts <= set(range(1, 5)) and len(counts) > 1
  assert shapes <= set(palettes.SHAPES) and len(shapes) >= 2
  assert tables <= set(palettes.TABLE_COLORS.values())


def test_same_seed_same_first_frame_and_seeds_differ(facts):
  first = facts["frames"][("train", FRAME_SEEDS[0])]["rgb"]
  np.testing.assert_array_equal(facts["again"], first)
  assert not np.array_equal(first, facts["frames"][("train", FRAME_SEEDS[1])]["rgb"])


def test_success_detection_on_scripted_states(facts):
  s = facts["success"]
  assert s["push"] == {"on_target": True, "off_target": False}
  assert s["pick"] == {"at_goal_not_grasped": False, "on_table": False}
  assert s["place"] == {"in_bin": True, "above_bin": False, "beside_bin": False}


@pytest.mark.parametrize("task", envs.TASKS)
def test_expert_solves_the_task(facts, task):
  assert facts["expert"][task] == [True] * len(EXPERT_SEEDS)


@pytest.mark.parametrize("task", envs.TASKS)
def test_no_milestone_at_reset_and_the_expert_reaches_every_one(facts, task):
  m = len(envs.MILESTONES[task])
  assert facts["milestones"][task] == [([False] * m, [True] * m)] * len(EXPERT_SEEDS)


@pytest.mark.parametrize("task", envs.TASKS)
def test_expert_acts_on_the_state_alone(facts, task):
  # Its actions are a function of the state it is shown, not of the states it saw before: a policy can infer them.
  assert facts["memoryless"][task] < 1e-6


@pytest.mark.parametrize("task", envs.TASKS)
def test_expert_is_batched_over_envs(facts, task):
  batched, single = facts["batched"][task]
  assert batched.shape == (2, 7) and not np.allclose(batched[0], batched[1])
  np.testing.assert_allclose(batched, single, atol=1e-6)


def test_the_camera_model_projects_the_cube_onto_its_mask(facts):
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  for frame in facts["frames"].values():
    rows, cols = np.nonzero(frame["seg"] == seg_ids.CUBE)
    centroid = (2 * np.array([rows.mean(), cols.mean()]) + 1) / RESOLUTION - 1     # pixel centres in [-1, 1]
    row, col, _ = camera.project(frame["cube"].astype(np.float32))
    np.testing.assert_allclose([row, col], centroid, atol=2 / RESOLUTION)          # within a pixel


def test_the_camera_model_puts_its_target_at_the_centre_and_unprojects_what_it_projects():
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  row, col, depth = camera.project(np.asarray([camera.TARGET], np.float32))
  np.testing.assert_allclose([row[0], col[0]], [0, 0], atol=1e-6)
  assert depth[0] == pytest.approx(np.linalg.norm(np.subtract(camera.TARGET, camera.EYE)), rel=1e-6)
  points = np.random.default_rng(0).uniform((-0.2, -0.2, 0.0), (0.2, 0.2, 0.2), (50, 3)).astype(np.float32)
  row, col, depth = camera.project(points)
  np.testing.assert_allclose(np.asarray(camera.unproject(row, col, depth)), points, atol=1e-5)
  # Higher in the world is higher in the image (smaller row); the camera faces the robot, so the robot's left (+y)
  # is the image's right (larger col).
  base = np.asarray([[0.0, 0.0, 0.05]], np.float32)
  assert camera.project(base + (0, 0, 0.05))[0] < camera.project(base)[0]
  assert camera.project(base + (0, 0.05, 0))[1] > camera.project(base)[1]
