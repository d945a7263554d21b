"""Tests of closed-loop evaluation, the tables, the report and the grid (roboshape/eval, roboshape/stages.py)."""
import csv
import json
import os
import shutil

import ml_collections
import numpy as np
import pytest

from configs import common
from configs import reproduce
from roboshape import envs
from roboshape import rundir
from roboshape import stages
from roboshape.envs import state as state_lib
from roboshape.errors import UserError
from roboshape.eval import closed_loop
from roboshape.report import publish
from roboshape.report import report
from roboshape.report import results as results_lib
from roboshape.report import tables

HORIZON = 8


def _outcome(seed: int):
  """The fake env's script: even seeds succeed after 3 + seed % 4 steps, odd seeds run to the horizon."""
  return (True, 3 + seed % 4) if seed % 2 == 0 else (False, HORIZON)


class FakeWorkerError(Exception):
  pass


class FakePool:
  """The sim bridge's closed-loop surface (the frame dicts of roboshape/sim/__init__.py) with scripted episodes; can kill a 'worker' on a step.
  Push's milestones: "moved" after one step, "halfway" after two, "on_target" with success."""
  milestones = envs.MILESTONES["push"]

  def __init__(self, num_envs=2, crash_on_steps=(), crash_forever_seed=None, size=8):
    self.num_envs = num_envs
    self.crash_on_steps = set(crash_on_steps)
    self.crash_forever_seed = crash_forever_seed
    self.size = size
    self.steps = 0
    self.restarts = 0
    self.reset_seeds = []
    self.rendered = {}
    self.dead = False

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    return False

  def _frames(self):
    img = np.zeros((len(self.seeds), self.size, self.size, 3), np.uint8)
    for i, (s, t) in enumerate(zip(self.seeds, self.elapsed)):
      img[i, ..., 0] = s % 251
      img[i, ..., 1] = t
    return img

  def reset(self, seeds, render=None):
    assert not self.dead, "reset on a dead pool without restart()"
    assert 0 < len(seeds) <= self.num_envs
    self.rendered.update(zip(seeds, render if render is not None else [True] * len(seeds)))
    self.seeds = list(seeds)
    self.reset_seeds += list(seeds)
    self.elapsed = np.zeros(len(seeds), np.int32)
    self.done = np.zeros(len(seeds), bool)
    self.success = np.zeros(len(seeds), bool)
    return dict(image=self._frames(), state=self._state(), success=self.success.copy(),
                done=self.done.copy(), elapsed=self.elapsed.copy(), reached=self._reached())

  def _state(self):
    """The hand starts 30 cm from the cube (at the origin) along x and comes 5 cm nearer each step."""
    state = np.zeros((len(self.seeds), state_lib.DIM), np.float32)
    state[:, state_lib.slices()["tcp_pos"].start] = 0.3 - 0.05 * self.elapsed
    return state

  def _reached(self):
    return np.stack([self.elapsed >= 1, self.elapsed >= 2, self.success], axis=1)

  def step(self, actions):
    assert actions.shape == (len(self.seeds), 7) and actions.dtype == np.float32
    assert np.all(np.abs(actions) <= 1.0)
    self.steps += 1
    if self.steps in self.crash_on_steps or (self.crash_forever_seed in self.seeds and self.elapsed.max() >= 2):
      self.dead = True
      raise FakeWorkerError("worker 1 died\nSegmentation fault")
    for i, s in enumerate(self.seeds):
      if self.done[i]:
        continue
      self.elapsed[i] += 1
      ok, length = _outcome(s)
      if self.elapsed[i] >= length:
        self.done[i], self.success[i] = True, ok
    return dict(image=self._frames(), segmentation=np.zeros(self._frames().shape[:3], np.uint8),
                state=self._state(), success=self.success.copy(), done=self.done.copy(),
                elapsed=self.elapsed.copy(), reached=self._reached())

  def restart(self):
    self.restarts += 1
    self.dead = False


class FakePolicy:
  """act_batch returns out-of-range actions (the loop must clip them); records the batch sizes it saw."""

  def __init__(self, interrupt_after=None, inputs=("image",)):
    self.inputs = inputs
    self.batch_sizes = set()
    self.calls = 0
    self.interrupt_after = interrupt_after

  def reset(self, batch_size=1):
    self.batch_size = batch_size

  def reset_slots(self, indices, seeds=None):
    assert max(indices) < self.batch_size and (seeds is None or len(seeds) == len(indices))

  def act_batch(self, frames):
    self.calls += 1
    if self.interrupt_after is not None and self.calls > self.interrupt_after:
      raise KeyboardInterrupt
    assert set(frames) == set(self.inputs)
    frames = frames[self.inputs[0]]
    self.batch_sizes.add(frames.shape[0])
    return np.full((frames.shape[0], 7), 1.5, np.float32)


def _config(levels=("train", "L1"), num_seeds=2, rollouts=3):
  config = common.get_config("push", "savi", "tiny")
  config.eval.levels = levels
  config.eval.num_seeds = num_seeds
  config.eval.rollouts_per_seed = rollouts
  config.eval.seed_offset = 1000
  config.eval.videos_per_level = 1
  return config


def _expected(config):
  return {(r.level, r.seed): _outcome(r.seed) for r in closed_loop.rollout_plan(
      config.eval.levels, config.eval.num_seeds, config.eval.rollouts_per_seed, config.eval.seed_offset)}


# ----------------------------------------------------------------------------------------------- tables


PUSH = {("train", "dino"): (0.0, 0.0), ("train", "r3m"): (0.88, 0.07), ("train", "savi"): (0.69, 0.06),
        ("L1", "dino"): (0.0, 0.0), ("L1", "r3m"): (0.26, 0.06), ("L1", "savi"): (0.55, 0.02),
        ("L2", "dino"): (0.0, 0.0), ("L2", "r3m"): (0.70, 0.01), ("L2", "savi"): (0.60, 0.04),
        ("L3", "r3m"): (0.76, 0.01), ("L3", "savi"): (0.756, 0.08)}


def test_markdown_table_exact():
  expected = ("| | DINO | R3M | SAVi |\n"
              "| --- | --- | --- | --- |\n"
              "| none | 0.00 ± 0.00 | **0.88** ± 0.07 | 0.69 ± 0.06 |\n"
              "| L1 | 0.00 ± 0.00 | 0.26 ± 0.06 | **0.55** ± 0.02 |\n"
              "| L2 | 0.00 ± 0.00 | **0.70** ± 0.01 | 0.60 ± 0.04 |\n"
              "| L3 | - | **0.76** ± 0.01 | **0.76** ± 0.08 |\n")
  assert tables.render_markdown(PUSH, tables.sort_encoders(["savi", "r3m", "dino"])) == expected


def test_latex_table_exact():
  expected = "\n".join([
      r"\begin{table}[h]",
      r"\caption{Success rate of \textit{push}}",
      r"\label{tab:push}",
      r"\begin{center}",
      r"\begin{tabular}{|c||c|c|c|}",
      r"\hline",
      r" & DINO & R3M & SAVi \\",
      r"\hline",
      r"$\emptyset$ & 0.00 $\pm$ 0.00 & \textbf{0.88} $\pm$ 0.07 & 0.69 $\pm$ 0.06 \\",
      r"\hline",
      r"L1 & 0.00 $\pm$ 0.00 & 0.26 $\pm$ 0.06 & \textbf{0.55} $\pm$ 0.02 \\",
      r"\hline",
      r"L2 & 0.00 $\pm$ 0.00 & \textbf{0.70} $\pm$ 0.01 & 0.60 $\pm$ 0.04 \\",
      r"\hline",
      r"L3 & - & \textbf{0.76} $\pm$ 0.01 & \textbf{0.76} $\pm$ 0.08 \\",
      r"\hline",
      r"\end{tabular}",
      r"\end{center}",
      r"\end{table}", ""])
  assert tables.render_latex(PUSH, ("dino", "r3m", "savi"), caption=r"Success rate of \textit{push}",
                             label="tab:push") == expected


def test_all_zero_row_has_no_bold():
  cells = {("train", "savi"): (0.0, 0.0), ("train", "r3m"): (0.001, 0.0)}
  assert "**" not in tables.render_markdown(cells, ("r3m", "savi"), levels=("train",))


def test_summary_mean_std_over_seeds_and_crashes_left_out():
  recs = [dict(task="push", encoder="savi", level="L1", seed_index=s, rollout=r, seed=0, success=ok, length=5,
               ended="success" if ok else "horizon")
          for s, oks in enumerate([(1, 1, 0, 0), (1, 0, 0, 0)]) for r, ok in enumerate(oks)]
  recs.append(dict(recs[0], rollout=9, success=False, ended="worker_crash", length=0))
  (row,) = results_lib.summarize(recs)
  assert row["per_seed"] == [0.5, 0.25]
  assert row["mean"] == pytest.approx(0.375) and row["std"] == pytest.approx(0.125)
  assert (row["rollouts"], row["successes"], row["crashed"]) == (8, 3, 1)


# ------------------------------------------------------------------------------------------ closed loop


def test_seed_plan_disjoint_and_stable():
  plan = closed_loop.rollout_plan(("train", "L3"), 3, 100)
  seeds = [r.seed for r in plan if r.level == "train"]
  assert len(set(seeds)) == 300 and min(seeds) >= 10**9
  assert seeds == [r.seed for r in plan if r.level == "L3"]     # levels share layouts
  assert plan[101] == closed_loop.Rollout("train", 1, 1, 10**9 + 100_001)


def test_rollouts_crash_restart_keeps_finished():
  config = _config(levels=("L2",), num_seeds=1, rollouts=5)
  plan = closed_loop.rollout_plan(config.eval.levels, 1, 5, config.eval.seed_offset)
  pool, policy, got = FakePool(num_envs=2, crash_on_steps={4}), FakePolicy(), []
  closed_loop.run_rollouts(pool, policy, plan, lambda r, res, fr: got.append((r, res)),
                           worker_error=FakeWorkerError)
  # Wave 1 = seeds 1000 (success at step 3) and 1001 (horizon 8); the crash at step 4 kills 1001 in flight.
  assert pool.restarts == 1
  assert [r.seed for r, _ in got].count(1000) == 1                   # finished before the crash: kept, not re-run
  assert sorted(r.seed for r, _ in got) == [1000, 1001, 1002, 1003, 1004]
  assert pool.reset_seeds == [1000, 1001, 1001, 1002, 1003, 1004]   # only the in-flight rollout re-runs, alone
  for r, res in got:
    ok, length = _outcome(r.seed)
    reached = ["moved", "halfway"] + (["on_target"] if ok else [])
    # The hand's closest approach to the cube over the episode (30 cm, 5 cm nearer a step), and the first actions'
    # length: the policy's 1.5 clipped to 1 in each of x, y, z.
    closest = round(100 * abs(0.3 - 0.05 * min(length, 6)), 2)
    assert res == dict(success=ok, length=length, ended="success" if ok else "horizon", reached=reached,
                       closest_cube_cm=closest, first_move=round(float(np.sqrt(3)), 4))
  assert policy.batch_sizes == {2}                                   # the short last wave is padded


def test_a_policy_without_camera_inputs_renders_only_the_recorded_rollouts():
  plan = closed_loop.rollout_plan(("train",), 1, 5, 1000)
  for inputs, rendered in ((("image",), {1000, 1001, 1002, 1003, 1004}), (("state",), {1001, 1003})):
    pool, got = FakePool(num_envs=2), []
    closed_loop.run_rollouts(pool, FakePolicy(inputs=inputs), plan, lambda r, res, fr: got.append((r.seed, fr)),
                             record=[plan[1], plan[3]])
    assert {seed for seed, on in pool.rendered.items() if on} == rendered
    assert sorted(seed for seed, frames in got if frames is not None) == [1001, 1003]


def test_persistent_crash_reported_not_counted(tmp_path):
  config = _config(levels=("train",), num_seeds=1, rollouts=4)
  config.eval.max_retries = 1
  pool = FakePool(num_envs=2, crash_forever_seed=1001)
  closed_loop.evaluate(config, str(tmp_path), FakePolicy(), lambda level: pool, FakeWorkerError)
  data = json.load(open(tmp_path / "eval" / "results.json"))
  ended = {r["seed"]: r["ended"] for r in data["rollouts"]}
  assert ended == {1000: "success", 1001: "worker_crash", 1002: "success", 1003: "horizon"}
  (row,) = data["summary"]
  assert (row["rollouts"], row["crashed"], row["mean"]) == (3, 1, pytest.approx(2 / 3))
  assert "1 rollout(s) lost to simulator worker crashes" in open(tmp_path / "eval" / "table.md").read()


def test_schedule_splits_each_level_into_rollouts_to_run_and_videos_to_record_again(tmp_path):
  plan = closed_loop.rollout_plan(("train", "L1"), 1, 3, 1000)
  log = results_lib.ResultLog(str(tmp_path / "results.jsonl"))
  for seed, ended in ((1000, "success"), (1001, "worker_crash")):
    log.append(dict(level="train", seed_index=0, rollout=seed - 1000, seed=seed, success=ended == "success",
                    length=4, ended=ended))
  without_video = lambda r, logged: logged["ended"] == "worker_crash"   # only the crashed one "has" its video
  train, l1 = closed_loop.schedule(plan, log, 2, without_video)
  assert (train.level, l1.level) == ("train", "L1")
  assert [r.seed for r in train.todo] == [1002] and [r.seed for r in train.record] == [1000, 1001]
  assert [r.seed for r in train.missing] == [1000]          # logged and recorded, its video gone: recorded again
  assert (train.planned, train.done, train.successes) == (3, 1, 1)   # the crashed rollout is not counted
  assert [r.seed for r in l1.todo] == [1000, 1001, 1002] and not l1.missing
  assert (l1.planned, l1.done, l1.successes) == (3, 0, 0)
  assert [w.record for w in closed_loop.schedule(plan, log, 0, without_video)] == [[], []]


def test_a_recorded_rollout_gets_its_slot_video_and_a_slot_video_that_fails_leaves_the_rollout(tmp_path, capsys):
  config = _config(levels=("train",), num_seeds=1, rollouts=2)
  flipped = lambda frames: frames[:, :, ::-1]
  closed_loop.evaluate(config, str(tmp_path / "a"), FakePolicy(), lambda level: FakePool(), slot_video=flipped)
  assert sorted(os.listdir(tmp_path / "a" / "eval" / "videos")) == [
      "train_s1000_success.gif", "train_s1000_success.mp4", "train_s1000_success_slots.gif",
      "train_s1000_success_slots.mp4"]

  def no_checkpoint(frames):
    raise UserError("no SAVi checkpoint")

  capsys.readouterr()
  paths = closed_loop.evaluate(config, str(tmp_path / "b"), FakePolicy(), lambda level: FakePool(),
                               slot_video=no_checkpoint)
  assert sorted(os.listdir(tmp_path / "b" / "eval" / "videos")) == ["train_s1000_success.gif",
                                                                    "train_s1000_success.mp4"]
  assert "slot video of " in capsys.readouterr().out and len(json.load(open(paths["json"]))["rollouts"]) == 2


def test_evaluate_resumes_after_interrupt(tmp_path):
  config = _config()
  expected = _expected(config)
  with pytest.raises(KeyboardInterrupt):
    closed_loop.evaluate(config, str(tmp_path), FakePolicy(interrupt_after=12), lambda level: FakePool())
  kept = results_lib.ResultLog(str(tmp_path / "eval" / "results.jsonl")).records
  assert 0 < len(kept) < len(expected)
  pools = {}
  closed_loop.evaluate(config, str(tmp_path), FakePolicy(), lambda level: pools.setdefault(level, FakePool()))
  rerun = {(level, s) for level, p in pools.items() for s in p.reset_seeds}
  assert rerun and not rerun & {results_lib.key(r) for r in kept}      # finished rollouts are not re-run
  assert len(rerun) + len(kept) == len(expected)
  data = json.load(open(tmp_path / "eval" / "results.json"))
  assert {(r["level"], r["seed"]): (r["success"], r["length"]) for r in data["rollouts"]} == expected
  # The log of another policy (or of the same one run otherwise) is set aside with its videos, not resumed.
  before = sorted(os.listdir(tmp_path / "eval" / "videos"))
  pools = {}
  closed_loop.evaluate(config, str(tmp_path), FakePolicy(), lambda level: pools.setdefault(level, FakePool()),
                       fingerprint="other")
  assert {(level, s) for level, p in pools.items() for s in p.reset_seeds} == set(expected)   # all re-run
  assert os.path.exists(tmp_path / "eval" / "results.jsonl.stale")
  assert sorted(os.listdir(tmp_path / "eval" / "videos.stale")) == before and before
  assert sorted(os.listdir(tmp_path / "eval" / "videos")) == before                         # recorded anew


def test_the_fingerprint_names_the_checkpoints_and_the_control_settings(tmp_path):
  ckpt = rundir.checkpoints(rundir.policy_dir(str(tmp_path)))
  os.makedirs(os.path.join(ckpt, "500"))
  base = closed_loop.policy_fingerprint(str(tmp_path))
  control = dict(history=0, action="mean", noise=0.1)
  same = closed_loop.policy_fingerprint(str(tmp_path), control=dict(reversed(list(control.items()))))
  assert same == closed_loop.policy_fingerprint(str(tmp_path), control=control) != base
  # A log written while policy.eval had ensemble_decay (at its default) is the same policy run the same way.
  assert closed_loop.policy_fingerprint(str(tmp_path), control=dict(control, ensemble_decay=0.01)) == same
  assert closed_loop.policy_fingerprint(str(tmp_path), control=dict(control, action="sample")) != same
  assert closed_loop.policy_fingerprint(str(tmp_path), control=dict(control, history=1)) != same
  os.makedirs(os.path.join(ckpt, "1000"))
  assert closed_loop.policy_fingerprint(str(tmp_path)) != base      # another checkpoint: another policy


def _real_sim():
  """roboshape.sim, or a skip where the simulator bridge cannot be imported."""
  sim = pytest.importorskip("roboshape.sim")
  assert hasattr(sim, "SimPool"), "roboshape.sim imports but has no SimPool"
  return sim


class CrashOnce:
  """Wraps a real SimPool: kills its worker 0 (the bridge's test hook) just before the `at_step`-th step."""

  def __init__(self, pool, at_step):
    self.pool, self.at_step, self.steps = pool, at_step, 0
    self.num_envs, self.milestones = pool.num_envs, pool.milestones
    self.restarts = 0

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.pool.close()

  def reset(self, seeds, render=None):
    return self.pool.reset(seeds, render)

  def step(self, actions):
    self.steps += 1
    if self.steps == self.at_step:
      self.pool._crash_worker(0, "injected by test_eval")  # pylint: disable=protected-access
    return self.pool.step(actions)

  def restart(self):
    self.restarts += 1
    self.pool.restart()


@pytest.fixture(scope="module", params=["fake", "real"])
def evaluated(request, tmp_path_factory):
  """An evaluation of level L1, 2 seeds x 2 rollouts of 8-step episodes in 2 envs, a worker killed mid-wave.

  Runs twice: through the scripted FakePool (exact outcomes known, a worker 'dies' on step 3) and through the real
  sim workers (roboshape.sim; worker 0 killed before step 3; skipped where the bridge cannot be imported). The
  policy is the scripted FakePolicy: the rollout machinery, not the policy, is under test here.
  """
  real = request.param == "real"
  sim = _real_sim() if real else None
  workdir = str(tmp_path_factory.mktemp(f"eval_run_{request.param}"))
  config = _config(levels=("L1",), num_seeds=2, rollouts=2)
  config.eval.seed_offset = 10**9
  config.sim.num_workers = 2
  config.env.max_episode_steps = HORIZON
  pools = []
  def make_pool(level):
    if real:
      pool = CrashOnce(sim.SimPool(sim.EnvSpec.from_config(config, level=level), num_workers=2), at_step=3)
    else:
      pool = FakePool(size=64, crash_on_steps={3})
    pools.append(pool)
    return pool
  paths = closed_loop.evaluate(config, workdir, FakePolicy(), make_pool,
                               sim.SimWorkerError if real else FakeWorkerError)
  return config, workdir, paths, pools, real


def test_evaluate_writes_all_outputs(evaluated):
  config, workdir, paths, _, real = evaluated
  for p in paths.values():
    assert os.path.getsize(p) > 0, p
  data = json.load(open(paths["json"]))
  assert len(data["rollouts"]) == 4
  assert [r["level"] for r in data["summary"]] == ["L1"]
  assert all(r["ended"] in ("success", "horizon") and 0 < r["length"] <= HORIZON for r in data["rollouts"])
  if not real:
    assert {(r["level"], r["seed"]): (r["success"], r["length"]) for r in data["rollouts"]} == _expected(config)
  with open(paths["csv"]) as f:
    rows = list(csv.DictReader(f))
  assert len(rows) == 4 and rows[0]["task"] == "push" and rows[0]["encoder"] == "savi"
  milestones = open(paths["milestones"]).read()
  assert "| | rollouts | moved | halfway | on_target | failed |" in milestones
  successes = sum(r["success"] for r in data["rollouts"])
  for r, row in zip(data["rollouts"], rows):
    assert set(r["reached"]) <= set(envs.MILESTONES["push"]) and row["reached"] == "+".join(r["reached"])
    assert ("on_target" in r["reached"]) == r["success"]         # push's last milestone is its success
  if not real:  # moved after one step, halfway after two: every rollout; on target: the 2 successes
    assert successes == 2
    assert "| L1 | 4 | 1.00 (4/4) | 1.00 (4/4) | 0.50 (2/4) | 2 | 1.00 (2/2) | 1.00 (2/2) | 0.00 (0/2) |" in milestones
  md = open(paths["md"]).read()
  assert "| | SAVi |" in md and "| L1 |" in md
  assert r"\begin{tabular}{|c||c|}" in open(paths["tex"]).read()
  with open(paths["png"], "rb") as f:
    assert f.read(8) == b"\x89PNG\r\n\x1a\n"
  vids = sorted(os.listdir(os.path.join(workdir, "eval", "videos")))
  assert [v.split("_")[0] for v in vids if v.endswith(".mp4")] == ["L1"]
  assert len([v for v in vids if v.endswith(".gif")]) == 1
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  first = [v for v in vids if v.endswith(".mp4")][0]
  rollout = [r for r in data["rollouts"] if r["seed_index"] == 0 and r["rollout"] == 0][0]
  mp4 = imageio.mimread(os.path.join(workdir, "eval", "videos", first), memtest=False)
  assert len(mp4) == rollout["length"] + 1 and mp4[0].shape[:2] == (256, 256)   # every frame, upscaled 4x


def test_worker_killed_mid_evaluation_is_restarted(evaluated):
  _, workdir, _, pools, _ = evaluated
  assert len(pools) == 1 and pools[0].restarts == 1
  log = results_lib.ResultLog(os.path.join(workdir, "eval", "results.jsonl")).records
  # Every planned rollout is in the log exactly once, none lost to the crash.
  assert sorted(results_lib.key(r) for r in log) == [("L1", 10**9 + s * 100_000 + r) for s in range(2) for r in range(2)]
  assert all(r["ended"] != "worker_crash" for r in log)


# --------------------------------------------------------------------------------------- report and grid


def test_grid_configs_and_report_with_skipped_baseline(tmp_path, evaluated):
  _, run_dir, _, _, _ = evaluated
  config = reproduce.get_config("tiny")
  config.grid.encoders = ("savi", "r3m")
  runs = list(stages.grid_configs(config, str(tmp_path)))
  assert [(t, e) for t, e, _, _ in runs] == [("push", "savi"), ("push", "r3m")]
  for task, encoder, sub, sub_dir in runs:
    assert "grid" not in sub and sub.encoder == encoder and sub.name == f"{task}_{encoder}"
    assert sub.data.dir == os.path.join(str(tmp_path), "data", "push")
    assert sub_dir == os.path.join(str(tmp_path), f"push_{encoder}")
    assert "report" not in sub.stages and ("pretrain" in sub.stages) == (encoder == "savi")
  # The savi run has results; the r3m run was skipped by the grid for absent weights.
  os.makedirs(tmp_path / "push_savi" / "eval")
  with open(os.path.join(run_dir, "eval", "results.json")) as f:
    data = f.read()
  (tmp_path / "push_savi" / "eval" / "results.json").write_text(data)
  os.makedirs(tmp_path / "push_r3m")
  (tmp_path / "push_r3m" / "SKIPPED.json").write_text(json.dumps({"reason": "R3M weights not found"}))
  paths = report.build_report(config, str(tmp_path))
  md = open(paths["report.md"]).read()
  assert "- skipped: R3M on push: R3M weights not found" in md
  assert "- the paper's R3M column has no cell here (skipped on push: its line above says why)." in md
  assert md.count("R3M weights not found") == 1          # the reason once, beside the skipped cell's line
  assert "| | R3M | SAVi |" in md and "| none | - |" in md
  assert os.path.getsize(paths["overall.png"]) > 0 and os.path.getsize(paths["table_push.tex"]) > 0


def test_report_over_published_runs_reads_back_each_run_and_marks_the_missing_cells(tmp_path, evaluated):
  config, run_dir, _, _, _ = evaluated
  root = str(tmp_path / "results")
  publish.publish(config, run_dir, root)
  # The published results.csv gives back the run's own summary, crashed rollouts left out as there.
  keys = ("task", "encoder", "level", "mean", "std", "per_seed", "rollouts", "successes", "crashed")
  run = report.load_run("push", "savi", run_dir)
  back = report.load_published(os.path.join(root, "push_savi"))
  assert [{k: r[k] for k in keys} for r in back["summary"]] == [{k: r[k] for k in keys} for r in run["summary"]]
  assert (back["num_seeds"], back["rollouts_per_seed"], back["levels"]) == (2, 2, ["L1"])
  # A second published run, of another task and encoder (an older CSV without train_seed and reached): 1 of 2.
  os.makedirs(os.path.join(root, "pick_state"))
  with open(os.path.join(root, "pick_state", rundir.RESULTS_CSV), "w") as f:
    f.write("task,encoder,level,seed_index,rollout,seed,success,length,ended\n"
            "pick,state,L1,0,0,7,True,9,success\npick,state,L1,0,1,8,False,40,horizon\n")
  paths = report.build_published_report(root)
  assert paths["report.md"] == os.path.join(root, "report", "report.md")
  md = open(paths["report.md"]).read()
  assert "| L1 | - | **0.50** ± 0.00 |" in open(paths["table_pick.md"]).read()
  assert "## pick" in md and md.split("## pick")[1].count("- not published yet: SAVi\n") == 1
  assert "- not published yet: State\n" in md.split("## pick")[0].split("## push")[1]
  assert os.path.getsize(paths["overall.png"]) > 0
  # The overall table says which tasks each row averages, and that rows over different tasks are not compared.
  overall = {line.split(" | ")[0]: line.split(" | ")[-1] for line in md.split("## Overall")[1].splitlines()
             if line.startswith("| SAVi |") or line.startswith("| State |")}
  assert overall == {"| SAVi": "push |", "| State": "pick |"} and "not comparable" in md.split("## Overall")[1]
  # A run with training seeds beside the others; built twice, the report does not read its own pooled results.csv
  # (report/, where rows with and without a training seed now meet) as one more run.
  os.makedirs(os.path.join(root, "place_state"))
  with open(os.path.join(root, "place_state", rundir.RESULTS_CSV), "w") as f:
    f.write("task,encoder,train_seed,level,seed_index,rollout,seed,success,length,ended,reached\n"
            "place,state,0,L1,0,0,7,True,9,success,\nplace,state,1,L1,0,0,7,False,40,horizon,\n")
  md = open(report.build_published_report(root)["report.md"]).read()
  assert open(report.build_published_report(root)["report.md"]).read() == md
  assert "| L1 | - | **0.50** ± 0.50 |" in open(os.path.join(root, "report", "table_place.md")).read()


def test_report_over_published_runs_refuses_a_folder_without_any(tmp_path, capsys):
  os.makedirs(tmp_path / "empty")
  with pytest.raises(UserError, match="holds no published run"):
    report.build_published_report(str(tmp_path / "empty"))
  assert report.main(["report", str(tmp_path / "absent")]) == 2
  assert "is not a folder" in capsys.readouterr().err
  assert not os.path.exists(tmp_path / "absent") and os.listdir(tmp_path / "empty") == []


def test_grid_skips_baseline_on_user_error(tmp_path, monkeypatch):
  config = reproduce.get_config("tiny")
  config.grid.encoders = ("savi", "dino")
  config.stages = ("train_policy", "report")
  config.baselines.dino.path = str(tmp_path / "dino.pth")       # a file: the run starts, and its stage fails
  (tmp_path / "dino.pth").write_bytes(b"not a checkpoint")
  calls = []

  class Stage:
    @staticmethod
    def run(cfg, workdir):
      calls.append((cfg.encoder, workdir))
      if cfg.encoder == "dino":
        raise stages.UserError("DINO weights not found: set --config.baselines.dino.path")

  monkeypatch.setitem(stages.STAGE_RUNS, "train_policy", Stage.run)
  stages.run(config, str(tmp_path))
  assert [e for e, _ in calls] == ["savi", "dino"]
  md = open(tmp_path / "report" / "report.md").read()
  assert "- skipped: DINO on push: DINO weights not found" in md
  assert "- skipped: SAVi on push: no evaluation results" in md


def test_a_grid_skips_a_baseline_without_its_weight_file_before_any_run_starts(tmp_path, monkeypatch):
  config = reproduce.get_config("tiny")
  config.grid.encoders = ("savi", "r3m", "dino")
  config.stages = ("train_policy",)
  config.grid.publish = str(tmp_path / "published")
  config.baselines.r3m.path = str(tmp_path / "absent" / "model.pt")
  config.baselines.dino.path = str(tmp_path / "dino.pth")          # present: DINO runs
  (tmp_path / "dino.pth").write_bytes(b"not a checkpoint")
  calls = []

  class Stage:
    @staticmethod
    def run(cfg, workdir):
      calls.append((cfg.encoder, os.path.exists(os.path.join(
          rundir.grid_run_dir(str(tmp_path / "grid"), "push", "r3m"), rundir.SKIPPED_FILE))))

  monkeypatch.setitem(stages.STAGE_RUNS, "train_policy", Stage.run)
  stages.run(config, str(tmp_path / "grid"))
  assert calls == [("savi", True), ("dino", True)]                   # skipped before the first run started
  reason = f"R3M ResNet-50 weights not found at {tmp_path / 'absent' / 'model.pt'}; download the official file"
  skipped = json.load(open(tmp_path / "grid" / "push_r3m" / rundir.SKIPPED_FILE))["reason"]
  assert skipped.startswith(reason) and "\n" not in skipped
  assert publish.grid_record(config.grid.publish)["skipped"] == {"push_r3m": skipped}
  (tmp_path / "absent").mkdir()
  (tmp_path / "absent" / "model.pt").write_bytes(b"")            # the file is there now: R3M runs, unskipped
  calls.clear()
  stages.run(config, str(tmp_path / "grid"))
  assert [e for e, _ in calls] == ["savi", "r3m", "dino"]
  assert not os.path.exists(tmp_path / "grid" / "push_r3m" / rundir.SKIPPED_FILE)
  assert publish.grid_record(config.grid.publish)["skipped"] == {}


def test_a_full_disk_stops_the_grid_in_one_line_rather_than_skipping_the_run(tmp_path, monkeypatch):
  """A baseline's stage that meets a full disk (an OSError(ENOSPC) naming its file) is one DiskFull line naming the
  stage and the file, as every stage's is (stages.run), and it stops the grid: every later run would meet the same
  disk, so the run is not recorded as skipped and no report is written."""
  import errno  # pylint: disable=import-outside-toplevel
  from roboshape.errors import DiskFull  # pylint: disable=import-outside-toplevel
  config = reproduce.get_config("tiny")
  config.grid.encoders = ("savi", "dino")
  config.stages = ("train_policy", "report")
  config.baselines.dino.path = str(tmp_path / "dino.pth")       # a file: the run starts, and its stage fails
  (tmp_path / "dino.pth").write_bytes(b"not a checkpoint")
  dino_dir = rundir.grid_run_dir(str(tmp_path), "push", "dino")
  full = os.path.join(dino_dir, "policy", "summary.json")

  class Stage:
    @staticmethod
    def run(cfg, workdir):
      if cfg.encoder == "dino":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), full)

  monkeypatch.setitem(stages.STAGE_RUNS, "train_policy", Stage.run)
  with pytest.raises(DiskFull) as e:
    stages.run(config, str(tmp_path))
  assert str(e.value) == (f"disk full while the train_policy stage wrote {full}: what it wrote completely is kept. "
                          f"Free some space on that disk (keep {dino_dir}: the run resumes from it) and run the same "
                          "command again to resume.")
  assert not os.path.exists(os.path.join(dino_dir, rundir.SKIPPED_FILE)) and not os.path.exists(tmp_path / "report")
  assert rundir.read_stage_log(dino_dir)["train_policy"]["state"] == "running"      # status: "stopped", not done


def test_summary_over_training_seeds_pools_each_policys_evaluation_seeds():
  def records(train_seed, successes):
    return [dict(task="push", encoder="state", train_seed=train_seed, level="train", seed_index=i // 2, rollout=i % 2,
                 seed=i, success=ok, length=5, ended="success" if ok else "horizon") for i, ok in enumerate(successes)]
  # Policy 0: 3 of 4 rollouts over its two evaluation seeds; policy 1: 1 of 4.
  (row,) = results_lib.summarize(records(0, [1, 1, 1, 0]) + records(1, [0, 1, 0, 0]))
  assert row["over"] == "training seeds" and row["per_seed"] == [0.75, 0.25]
  assert (row["mean"], row["std"], row["rollouts"], row["successes"]) == (0.5, 0.25, 8, 4)
  (row,) = results_lib.summarize(records(0, [1, 1, 1, 0]))                 # one policy: over evaluation seeds
  assert row["over"] == "evaluation seeds" and row["per_seed"] == [1.0, 0.5]


def test_evaluate_each_training_seed_into_its_own_log_then_one_table(tmp_path):
  config = _config(levels=("train",), num_seeds=2, rollouts=2)
  config.policy.train_seeds = (0, 1)
  workdir = str(tmp_path)
  for i, seed in enumerate((0, 1)):
    closed_loop.evaluate(config, workdir, FakePolicy(), lambda level: FakePool(), FakeWorkerError,
                         fingerprint=f"policy{seed}", train_seed=seed,
                         videos_per_level=1 if i == 0 else 0)
  for seed in (0, 1):
    logged = results_lib.read_log(rundir.rollout_log(workdir, seed))
    assert len(logged) == 4 and {r["train_seed"] for r in logged} == {seed}
  data = json.load(open(tmp_path / "eval" / "results.json"))
  assert len(data["rollouts"]) == 8
  (row,) = data["summary"]
  rate = np.mean([ok for ok, _ in _expected(config).values()])
  assert row["over"] == "training seeds" and row["per_seed"] == [rate, rate] and row["std"] == 0.0
  assert "over 2 training seed(s)" in open(tmp_path / "eval" / "table.md").read()
  with open(tmp_path / "eval" / "results.csv") as f:
    assert {r["train_seed"] for r in csv.DictReader(f)} == {"0", "1"}
  assert len(os.listdir(tmp_path / "eval" / "videos")) >= 1
  assert all("s1000_" in name for name in os.listdir(tmp_path / "eval" / "videos"))   # the first policy's only
  # Rerun otherwise (new fingerprints): the first policy's set-aside log takes the old videos along and records new
  # ones; the second policy's, which records none, leaves the new videos where they are.
  videos = sorted(os.listdir(tmp_path / "eval" / "videos"))
  for i, seed in enumerate((0, 1)):
    closed_loop.evaluate(config, workdir, FakePolicy(), lambda level: FakePool(), FakeWorkerError,
                         fingerprint=f"other{seed}", train_seed=seed,
                         videos_per_level=1 if i == 0 else 0)
  assert sorted(os.listdir(tmp_path / "eval" / "videos")) == videos
  assert sorted(os.listdir(tmp_path / "eval" / "videos.stale")) == videos


def test_grid_sets_training_seeds_per_task_and_publish_by_variant():
  small = reproduce.get_config("small")
  assert small.grid.publish == "results/small" and reproduce.get_config("tiny").grid.publish == ""
  assert set(small.grid.tasks) == set(common.TASKS)
  assert {"savi", "ae", "objects", "state", "savi+proprio", "ae+proprio"} <= set(small.grid.encoders)
  runs = list(stages.grid_configs(small, "/w"))
  seeds = {(task, column): tuple(sub.policy.train_seeds) for task, column, sub, _ in runs}
  assert set(seeds.values()) == {(0, 1, 2)} and len(seeds) == 3 * len(small.grid.encoders)   # every cell, every task
  assert tuple(small.pretrain.train_seeds) == (0, 1, 2)
  assert tuple(reproduce.get_config("tiny").pretrain.train_seeds) == ()
  # each run is its task x column's own config (place: a sampled mode, one frame at control time; +proprio: the
  # encoder with policy.proprio) but for what the grid sets on purpose: the shared dataset, the seeds, the stages,
  # and for a +proprio column the plain column's run, whose pretrained encoder it serves
  def flat(d, prefix=""):
    out = {}
    for k, v in d.items():
      out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
    return out
  for task, column, sub, sub_dir in runs:
    a, b = flat(sub.to_dict()), flat(common.get_config(task, column, "small").to_dict())
    differ = {k for k in set(a) | set(b) if a.get(k) != b.get(k)}
    assert differ <= {"data.dir", "policy.train_seeds", "pretrain.train_seeds", "pretrain.from_workdir", "stages"}, (
        task, column, differ)
    assert sub_dir == f"/w/{task}_{column}" and sub.name == f"{task}_{column}"
  proprio = {(task, column): sub for task, column, sub, _ in runs if column.endswith("+proprio")}
  assert len(proprio) == 6
  for (task, column), sub in proprio.items():
    plain = column.split("+")[0]
    assert (sub.encoder, sub.policy.proprio) == (plain, True)
    assert sub.pretrain.from_workdir == f"/w/{task}_{plain}" and "pretrain" not in sub.stages
  plain_savi = next(sub for task, column, sub, _ in runs if (task, column) == ("push", "savi"))
  assert plain_savi.pretrain.from_workdir == "" and "pretrain" in plain_savi.stages and not plain_savi.policy.proprio
  # the plain columns of every task first (SAVi and the AE first within a task), then the +proprio columns, each
  # waiting in lanes for the plain run whose encoder it serves
  order = [(t, c) for t, c, _, _ in runs]
  plain = [c for c in small.grid.encoders if "+" not in c]
  assert order[:len(plain)] == [("push", c) for c in plain] and plain[:2] == ["savi", "ae"]
  assert order[len(plain):2 * len(plain)] == [("pick", c) for c in plain]
  assert [c for _, c in order[-6:]] == ["savi+proprio", "ae+proprio"] * 3
  assert stages.pretrained_from(runs)["/w/place_ae+proprio"] == "/w/place_ae"
  evals = {task: (sub.policy.eval.action, sub.policy.eval.history) for task, _, sub, _ in runs}
  assert evals == {"push": ("mean", 0), "pick": ("mean", 0), "place": ("sample", 1)}
  steps = {task: sub.policy.train.steps for task, _, sub, _ in runs}
  assert steps == {"push": 5000, "pick": 5000, "place": 15000}


def test_a_proprio_column_without_its_plain_column_pretrains_its_own_encoder():
  config = reproduce.get_config("small")
  config.grid.tasks, config.grid.encoders = ("push",), ("ae+proprio", "state")
  runs = list(stages.grid_configs(config, "/w"))
  assert [c for _, c, _, _ in runs] == ["state", "ae+proprio"]          # a column beyond the paper's comes last
  (_, column, sub, _) = runs[1]
  assert (column, sub.encoder, sub.policy.proprio, sub.pretrain.from_workdir) == ("ae+proprio", "ae", True, "")
  assert "pretrain" in sub.stages and stages.pretrained_from(stages.grid_configs(config, "/w")) == {}


def test_a_grid_runs_no_skipped_cell_and_a_proprio_column_of_a_skipped_one_pretrains_its_own():
  config = reproduce.get_config("small")
  config.grid.tasks, config.grid.encoders = ("place", "push"), ("savi", "ae", "objects", "savi+proprio")
  config.grid.skip = ("place_savi", "place_ae")
  runs = {(t, c): sub for t, c, sub, _ in stages.grid_configs(config, "/w")}
  assert list(runs) == [("place", "objects"), ("push", "savi"), ("push", "ae"), ("push", "objects"),
                        ("place", "savi+proprio"), ("push", "savi+proprio")]
  place, push = runs["place", "savi+proprio"], runs["push", "savi+proprio"]
  assert (place.pretrain.from_workdir, "pretrain" in place.stages) == ("", True)
  assert (push.pretrain.from_workdir, "pretrain" in push.stages) == ("/w/push_savi", False)
  assert stages.pretrained_from(stages.grid_configs(config, "/w")) == {"/w/push_savi+proprio": "/w/push_savi"}


def test_a_column_with_options_labels_its_rollouts_its_tables_and_its_published_folder(tmp_path):
  config = common.get_config("push", "savi+proprio", "tiny")
  config.eval.levels, config.eval.num_seeds, config.eval.rollouts_per_seed = ("train",), 1, 2
  workdir = str(tmp_path / "push_savi+proprio")
  rundir.save_config(config, workdir)
  # rollouts logged under the plain encoder's name (before runs were labelled by column) are labelled too
  records = [dict(task="push", encoder="savi", level="train", seed_index=0, rollout=r, seed=1000 + r,
                  success=r == 0, length=5, ended="success" if r == 0 else "horizon") for r in range(2)]
  closed_loop.write_outputs(config, workdir, records)
  with open(os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_CSV), newline="") as f:
    assert [r["encoder"] for r in csv.DictReader(f)] == ["savi+proprio"] * 2
  with open(os.path.join(rundir.eval_dir(workdir), "table.md")) as f:
    assert f.readline() == "### push: success rate, SAVi+proprio\n"
  root = str(tmp_path / "results")
  assert publish.publish(config, workdir, root) == os.path.join(root, "push_savi+proprio")
  with open(report.build_published_report(root)["table_push.md"]) as f:
    assert f.read().splitlines()[:3] == ["| | SAVi+proprio |", "| --- | --- |", "| none | **0.50** ± 0.00 |"]


def _published_cell(root, name: str, identity=None) -> None:
  """A published cell <root>/<name>/ of one rollout, recording dataset `identity` (none: no dataset.json)."""
  task, encoder = name.split("_", 1)
  os.makedirs(os.path.join(root, name))
  with open(os.path.join(root, name, rundir.RESULTS_CSV), "w") as f:
    f.write(f"task,encoder,level,seed_index,rollout,seed,success,length,ended\n"
            f"{task},{encoder},train,0,0,7,True,9,success\n")
  if identity:
    with open(os.path.join(root, name, rundir.DATASET_FILE), "w") as f:
      json.dump({"identity": identity, "name": f"roboshape_{task}"}, f)


def test_the_published_report_lists_its_grids_cells_not_published_yet_and_those_it_skipped(tmp_path):
  root = str(tmp_path / "results")
  _published_cell(root, "push_ae", "aaaa")
  publish.record_grid(root, ("push", "pick"), ("savi", "ae", "r3m"))
  publish.record_skip(root, "push", "r3m", "R3M weights not found: see README.md")
  publish.record_skip(root, "pick", "r3m", "R3M weights not found: see README.md")
  publish.record_skip(root, "pick", "r3m", None)                     # ran since: no longer skipped
  publish.record_grid(root, ("push", "pick"), ("savi", "ae", "r3m"))   # the grid started again: the skip stays
  assert publish.grid_record(root) == dict(tasks=["push", "pick"], columns=["savi", "ae", "r3m"],
                                           skipped={"push_r3m": "R3M weights not found: see README.md"})
  paths = report.build_published_report(root)
  md = open(paths["report.md"]).read()
  push, pick = md.split("## push\n")[1].split("## pick\n")
  assert open(paths["table_pick.md"]).read().startswith("| | R3M | AE | SAVi |")
  assert "- not published yet: SAVi\n" in push and "- skipped: R3M on push: R3M weights not found: see README.md" in push
  assert "- not published yet: R3M, AE, SAVi\n" in pick and "skipped" not in pick.split("The paper's")[0]
  publish.record_grid(root, ("place",), ("ae", "savi+proprio"))   # a grid over part of the cells adds, never narrows
  assert publish.grid_record(root) == dict(tasks=["push", "pick", "place"],
                                           columns=["savi", "ae", "r3m", "savi+proprio"],
                                           skipped={"push_r3m": "R3M weights not found: see README.md"})
  md = open(report.build_published_report(root)["report.md"]).read()
  pick = md.split("## pick\n")[1].split("## place\n")[0]
  assert "- not published yet: R3M, AE, SAVi, SAVi+proprio\n" in pick
  with open(os.path.join(root, publish.GRID_FILE), "w") as f:
    f.write("{")
  with pytest.raises(UserError, match=r"grid\.json is damaged \(JSONDecodeError\): delete it"):
    report.build_published_report(root)


def test_the_published_report_refuses_cells_of_one_task_trained_on_different_datasets(tmp_path, capsys):
  root = str(tmp_path / "results")
  for name, identity in (("push_savi", "aaaa"), ("push_ae", "aaaa"), ("push_state", "bbbb"), ("pick_state", "cccc"),
                         ("pick_savi", None)):
    _published_cell(root, name, identity)
  assert report.main(["report", root]) == 2
  line = capsys.readouterr().err.strip()
  assert line == ("roboshape: error: the push cells were trained on different datasets (push_ae, push_savi on "
                  "dataset aaaa; push_state on dataset bbbb): publish every cell of a task from runs on one dataset "
                  f"(one grid), or move the odd cells out of {root}.")
  assert sorted(os.listdir(root)) == ["pick_savi", "pick_state", "push_ae", "push_savi", "push_state"]
  assert not any(os.path.exists(os.path.join(root, n, "README.md")) for n in os.listdir(root))   # nothing written
  # one dataset per task (a cell without a record is not compared): the report is built
  shutil.move(os.path.join(root, "push_state"), str(tmp_path / "push_state"))
  assert report.main(["report", root]) == 0
  md = open(os.path.join(root, "report", "report.md")).read()
  push, pick = md.split("## push\n")[1].split("## pick\n")
  # each task's section names its one dataset and how many of its published cells record it
  assert "- dataset: `aaaa` (its identity, a hash over the shards' checksums), recorded by 2 of the 2 published " \
      "cell(s) in their dataset.json" in push
  assert "- dataset: `cccc` (its identity, a hash over the shards' checksums), recorded by 1 of the 2 published " \
      "cell(s) in their dataset.json" in pick and pick.count("- dataset:") == 1
