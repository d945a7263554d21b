"""The stage log, `python -m roboshape.status` and publishing a finished run's results (roboshape/report/publish.py)."""
import json
import os
import subprocess
import sys

import pytest

from configs import common
from roboshape import fileio
from roboshape import rundir
from roboshape import status
from roboshape.errors import UserError
from roboshape.report import publish

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _dead_pid() -> int:
  proc = subprocess.Popen([sys.executable, "-c", "pass"])
  proc.wait()
  return proc.pid


def test_the_stage_log_sums_the_seconds_of_resumed_attempts(tmp_path):
  workdir = str(tmp_path)
  assert rundir.read_stage_log(workdir) == {}
  rundir.record_stage(workdir, "collect", "running")
  entry = rundir.read_stage_log(workdir)["collect"]
  assert entry["state"] == "running" and entry["pid"] == os.getpid()
  rundir.record_stage(workdir, "collect", "done", 12.04)
  log = rundir.read_stage_log(workdir)
  log["collect"]["started"] = "2026-01-01T00:00:00"      # a first attempt long ago
  fileio.atomic_write_json(rundir.stage_log_path(workdir), log)
  rundir.record_stage(workdir, "collect", "running")      # resumed: it was done, runs again (and skips its work)
  rundir.record_stage(workdir, "collect", "done", 0.5)
  entry = rundir.read_stage_log(workdir)["collect"]
  assert entry["state"] == "done" and entry["seconds"] == pytest.approx(12.5) and "pid" not in entry
  assert entry["started"] == "2026-01-01T00:00:00"         # the first attempt's start, not the resume's


def test_the_stage_log_counts_a_killed_attempt_to_its_last_beat_in_seconds_and_core_seconds(tmp_path):
  workdir, cores = str(tmp_path), len(os.sched_getaffinity(0))
  rundir.record_stage(workdir, "train_policy", "running")
  log = rundir.read_stage_log(workdir)
  entry = log["train_policy"]
  assert entry["cores"] == cores and entry["beat"] == entry["attempt"]
  entry.update(pid=_dead_pid(), cores=3, beat=entry["attempt"] + 100.0)   # killed 100 s in, on 3 cores
  with open(rundir.stage_log_path(workdir), "w") as f:
    json.dump(log, f)
  rundir.record_stage(workdir, "train_policy", "running")               # the resume adds the killed attempt
  entry = rundir.read_stage_log(workdir)["train_policy"]
  assert (entry["seconds"], entry["core_seconds"], entry["cores"]) == (100.0, 300.0, cores)
  rundir.record_stage(workdir, "train_policy", "done", 20.0)
  entry = rundir.read_stage_log(workdir)["train_policy"]
  assert (entry["seconds"], entry["core_seconds"]) == (120.0, 300.0 + 20.0 * cores)
  assert not {"pid", "beat", "attempt"} & set(entry)
  assert rundir.logged_time({"state": "done", "seconds": 7.0}) == (7.0, 7.0)   # logged before cores were: one core
  open_entry = dict(state="running", seconds=5.0, core_seconds=10.0, cores=2, attempt=100.0, beat=130.0)
  assert rundir.logged_time(open_entry) == (35.0, 70.0)                 # an open attempt, up to its last beat


def test_the_stage_clock_beats_while_a_stage_runs_and_an_interrupted_attempt_keeps_its_time(tmp_path):
  import time  # pylint: disable=import-outside-toplevel
  workdir = str(tmp_path)
  with pytest.raises(KeyboardInterrupt):
    with rundir.stage_clock(workdir, "evaluate", every=0.01):
      time.sleep(0.2)
      raise KeyboardInterrupt
  entry = rundir.read_stage_log(workdir)["evaluate"]
  assert entry["state"] == "running" and entry["beat"] - entry["attempt"] >= 0.2   # its last beat: when it stopped
  with rundir.stage_clock(workdir, "evaluate", every=60.0):
    pass
  entry = rundir.read_stage_log(workdir)["evaluate"]
  assert entry["state"] == "done" and 0.2 <= entry["seconds"] < 5.0
  assert entry["core_seconds"] == pytest.approx(entry["seconds"] * len(os.sched_getaffinity(0)), abs=0.2)


def test_compute_sums_core_hours_per_cell_and_row_with_the_collection_apart(tmp_path):
  from roboshape.report import compute  # pylint: disable=import-outside-toplevel
  logs = {("push", "savi"): {"collect": dict(state="done", seconds=1800.0, core_seconds=3600.0),
                             "train_policy": dict(state="done", seconds=3600.0, core_seconds=3600.0),
                             "evaluate": dict(state="done", seconds=900.0)},            # before cores: one core
          ("push", "state"): {"train_policy": dict(state="running", seconds=1800.0, core_seconds=1800.0)}}
  runs = []
  for (task, column), log in logs.items():
    folder = tmp_path / f"{task}_{column}"
    folder.mkdir()
    (folder / "stages.json").write_text(json.dumps(log))
    runs.append((task, column, str(folder)))
  runs.append(("pick", "savi", str(tmp_path / "pick_savi")))                            # not run yet
  assert compute.core_hours(runs[0][2]) == {"collect": 1.0, "train_policy": 1.0, "evaluate": 0.25}
  text = compute.render(runs, ["push", "pick"], ["savi", "state"])
  assert "| push | 1.2 | 0.5 | 1.0 | 2.8 |" in text and "| pick | - | - | 0.0 | 0.0 |" in text
  assert text.rstrip().endswith("2.8 core-hours in all.")


def _grid_workdir(tmp_path):
  config = common.get_config("push", "state", "tiny")
  config.grid = dict(tasks=("push", "pick"), encoders=("state", "objects"), publish="")
  workdir = str(tmp_path / "grid")
  rundir.save_config(config, workdir)
  return config, workdir


def test_status_of_a_grid_says_done_running_stopped_skipped_and_pending(tmp_path):
  config, workdir = _grid_workdir(tmp_path)
  stages = [s for s in config.stages if s != "report"]
  done = rundir.grid_run_dir(workdir, "push", "state")
  for i, stage in enumerate(stages):
    rundir.record_stage(done, stage, "running")
    rundir.record_stage(done, stage, "done", 60.0 * (i + 1))
  running = rundir.grid_run_dir(workdir, "push", "objects")
  rundir.record_stage(running, "collect", "done", 5.0)
  rundir.record_stage(running, "cache", "running")                    # this process: alive
  stopped = rundir.grid_run_dir(workdir, "pick", "state")
  rundir.record_stage(stopped, "collect", "running")
  log = rundir.read_stage_log(stopped)
  log["collect"]["pid"] = _dead_pid()                                  # killed mid-stage
  with open(rundir.stage_log_path(stopped), "w") as f:
    json.dump(log, f)
  skipped = rundir.grid_run_dir(workdir, "pick", "objects")
  os.makedirs(skipped)
  with open(os.path.join(skipped, rundir.SKIPPED_FILE), "w") as f:
    json.dump({"reason": "no weights"}, f)
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  assert {k: r["state"] for k, r in rows.items()} == {
      ("push", "state"): "done", ("push", "objects"): "running", ("pick", "state"): "stopped",
      ("pick", "objects"): "skipped"}
  assert rows[("push", "state")]["seconds"] == pytest.approx(60.0 * sum(range(1, len(stages) + 1)))
  assert rows[("push", "objects")]["stages"]["cache"] == "running"
  assert rows[("push", "objects")]["stages"]["train_policy"] == "pending"
  text = status.render(list(rows.values()))
  assert "| push | state | done | 1m00s | 2m00s |" in text
  assert f"| {rows[('push', 'state')]['core_hours']:.2f} |" in text.splitlines()[2]
  assert rows[("push", "state")]["core_hours"] == pytest.approx(
      60.0 * sum(range(1, len(stages) + 1)) * len(os.sched_getaffinity(0)) / 3600)
  assert "1 done, 1 running, 1 skipped, 1 stopped of 4 run(s)" in text
  # A run none of whose stages started is pending; so is one whose dataset alone the grid collected for it (the
  # grid's own collection, before its lanes start), while one that ended between two later stages has stopped.
  os.remove(rundir.stage_log_path(stopped))
  assert {r["state"] for r in status.workdir_status(workdir) if r["task"] == "pick"} == {"pending", "skipped"}
  rundir.record_stage(stopped, "collect", "running")
  rundir.record_stage(stopped, "collect", "done", 5.0)
  assert {r["state"] for r in status.workdir_status(workdir) if r["task"] == "pick"} == {"pending", "skipped"}
  rundir.record_stage(stopped, stages[1], "running")
  rundir.record_stage(stopped, stages[1], "done", 5.0)
  assert {r["state"] for r in status.workdir_status(workdir) if r["task"] == "pick"} == {"stopped", "skipped"}


def test_status_says_how_long_the_grid_itself_has_run_over_its_restarts(tmp_path, capsys):
  _, workdir = _grid_workdir(tmp_path)
  assert status.grid_time(workdir) is None                             # a grid that never ran
  rundir.record_stage(workdir, rundir.GRID_CLOCK, "running")
  log = rundir.read_stage_log(workdir)
  log[rundir.GRID_CLOCK].update(pid=_dead_pid(), beat=log[rundir.GRID_CLOCK]["attempt"] + 3600.0)
  with open(rundir.stage_log_path(workdir), "w") as f:                 # killed after an hour
    json.dump(log, f)
  started = log[rundir.GRID_CLOCK]["started"]
  assert status.grid_time(workdir) == (
      f"The grid has run 1h00m of wall time since {started}, over its restarts (stopped).")
  rundir.record_stage(workdir, rundir.GRID_CLOCK, "running")           # restarted: the hour is kept
  assert status.grid_time(workdir).startswith("The grid has run 1h00m of wall time") and "(running now)" in (
      status.grid_time(workdir))
  rundir.record_stage(workdir, rundir.GRID_CLOCK, "done", 1800.0)
  line = status.grid_time(workdir)
  assert line.startswith(f"The grid has run 1h30m of wall time since {started}, over its restarts (finished 20")
  assert status.main(["status", workdir]) == 0 and capsys.readouterr().out.rstrip().endswith(line)


def test_status_estimates_the_core_hours_left_from_the_finished_stages_of_each_column_or_encoder(tmp_path):
  config = common.get_config("push", "state", "tiny")
  config.grid = dict(tasks=("push", "pick"), encoders=("state", "objects", "state+proprio"), publish="")
  workdir = str(tmp_path / "grid")
  rundir.save_config(config, workdir)
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  assert status.render(list(rows.values())).endswith(   # nothing finished yet: no rate, so no sum of nothing
      "No estimate of the core-hours left yet: no stage of these runs' columns or encoders has finished or saved "
      "work to take a rate from.")
  steps = int(rows[("push", "state")]["config"].policy.train.steps)
  assert status.work(rows[("push", "state")]["config"], rows[("push", "state")]["run_dir"], "train_policy") == (
      0, steps)
  # push x state finished: its policy took 2 core-hours, its evaluation 1 (in core-seconds, as the stage log holds)
  done = rundir.grid_run_dir(workdir, "push", "state")
  os.makedirs(done)
  log = {stage: dict(state="done", seconds=1.0, core_seconds=1.0) for stage in rows[("push", "state")]["stages"]}
  log["train_policy"]["core_seconds"], log["evaluate"]["core_seconds"] = 7200.0, 3600.0
  with open(rundir.stage_log_path(done), "w") as f:
    json.dump(log, f)
  # pick x state trained half its steps: half the policy's 2 core-hours and the whole evaluation's hour are left
  half = rundir.grid_run_dir(workdir, "pick", "state")
  os.makedirs(os.path.join(rundir.checkpoints(rundir.policy_dir(half)), str(steps // 2)))
  rundir.record_stage(half, "collect", "done", 1.0)
  rundir.record_stage(half, "cache", "done", 1.0)                      # it ended between two stages: stopped
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  assert rows[("pick", "state")]["left"] == pytest.approx((steps - steps // 2) / steps * 2.0 + 1.0)
  # a column with options takes its encoder's rate (push and pick x state+proprio: 3 each); a column nothing
  # finished of has no estimate
  assert rows[("push", "state+proprio")]["left"] == pytest.approx(3.0)
  assert rows[("push", "objects")]["left"] is None and rows[("push", "state")]["left"] is None
  text = status.render(list(rows.values()))
  assert [line for line in text.splitlines() if line.startswith("| pick | state | stopped |")][0].endswith(
      f"| ~{rows[('pick', 'state')]['left']:.1f} |")
  assert text.endswith(f"About {3.0 + 3.0 + rows[('pick', 'state')]['left']:.1f} core-hours left, at the "
                       "training stages' own pace and the rates of the finished stages (collections and caches not "
                       "counted); no rate yet for push x objects, pick x objects.")
  # on two lanes, the same core-hours are half as many hours of wall time
  assert status.render(list(rows.values()), lanes=2).endswith(
      f"no rate yet for push x objects, pick x objects; at least {(6.0 + rows[('pick', 'state')]['left']) / 2:.1f} "
      "hours of wall time on the grid's 2 lanes (grid.lanes, one core each).")


def test_a_column_no_run_of_the_grid_rates_takes_the_rate_of_the_cells_published_where_the_grid_publishes(tmp_path):
  config = common.get_config("push", "state", "tiny")
  published = str(tmp_path / "published")
  config.grid = dict(tasks=("push", "pick"), encoders=("state", "objects"), publish=published)
  workdir = str(tmp_path / "grid")
  rundir.save_config(config, workdir)
  # an objects cell published earlier: its policy took 1 core-hour, its evaluation half of one
  cell = os.path.join(published, rundir.grid_cell("push", "objects"))
  cell_config = common.get_config("push", "objects", "tiny")
  rundir.save_config(cell_config, cell)
  log = {stage: dict(state="done", seconds=1.0, core_seconds=1.0) for stage in cell_config.stages}
  log["train_policy"]["core_seconds"], log["evaluate"]["core_seconds"] = 3600.0, 1800.0
  with open(rundir.stage_log_path(cell), "w") as f:
    json.dump(log, f)
  os.makedirs(os.path.join(published, "report"))                   # a folder that is no cell is passed over
  assert [(r["task"], r["encoder"], r["state"]) for r in status.published_rows(config)] == [
      ("push", "objects", "done")]
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  for task in ("push", "pick"):
    assert rows[(task, "objects")]["left"] == pytest.approx(1.5) and rows[(task, "objects")]["published_rate"]
    assert rows[(task, "state")]["left"] is None                    # no state cell anywhere: no rate
  assert status.render(list(rows.values())).endswith(
      "About 3.0 core-hours left, at the training stages' own pace and the rates of the finished stages "
      "(collections and caches not counted); push x objects, pick x objects partly at the rates of the cells "
      "published where the grid publishes (grid.publish), perhaps on another machine; no rate yet for push x "
      "state, pick x state.")
  # a run of the grid's own that finished takes precedence over the published cell
  done = rundir.grid_run_dir(workdir, "push", "objects")
  os.makedirs(done)
  with open(rundir.stage_log_path(done), "w") as f:
    json.dump(dict(log, train_policy=dict(state="done", seconds=1.0, core_seconds=7200.0)), f)
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  assert rows[("pick", "objects")]["left"] == pytest.approx(2.5) and not rows[("pick", "objects")]["published_rate"]
  config.grid.publish = ""
  assert status.published_rows(config) == [] and status.published_rows(cell_config) == []


def test_a_running_training_stage_is_estimated_at_its_own_pace_between_checkpoints_of_this_attempt(tmp_path):
  config = common.get_config("push", "state", "tiny")
  config.grid = dict(tasks=("push", "pick"), encoders=("state",), publish="")
  config.policy.train_seeds, config.policy.train.steps = (0, 1), 1000
  workdir = str(tmp_path / "grid")
  rundir.save_config(config, workdir)
  run = rundir.grid_run_dir(workdir, "push", "state")
  rundir.record_stage(run, "train_policy", "running")                    # this process: alive, on these cores
  log = rundir.read_stage_log(run)
  entry = log["train_policy"]
  log["train_policy"]["seconds"] = log["train_policy"]["core_seconds"] = 9000.0   # earlier attempts, killed
  with open(rundir.stage_log_path(run), "w") as f:
    json.dump(log, f)
  seed_1 = rundir.checkpoints(rundir.policy_dir(run, 1))
  os.makedirs(os.path.join(rundir.checkpoints(rundir.policy_dir(run, 0)), "1000"))
  for step, written in ((200, 10.0), (300, 110.0)):                     # 100 steps in 100 s of this attempt
    os.makedirs(os.path.join(seed_1, str(step)))
    os.utime(os.path.join(seed_1, str(step)), (entry["attempt"] + written,) * 2)
  cores = entry["cores"]
  assert status.pace(config, run, "train_policy", entry["attempt"], cores) == (100.0 * cores, 100)
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  # push x state: 700 steps left at 1 s x cores a step (not the 9000 logged core-seconds over 1300 saved steps);
  # its evaluation and pick's whole run have no rate from anything finished: pick's training takes push's pace
  assert rows[("push", "state")]["left"] is None and rows[("pick", "state")]["left"] is None
  push_rate = 100.0 * cores / 100
  done_eval = rundir.grid_run_dir(workdir, "pick", "objects")             # another column's finished evaluation
  os.makedirs(done_eval)
  with open(rundir.stage_log_path(done_eval), "w") as f:
    json.dump({"evaluate": dict(state="done", seconds=360.0, core_seconds=360.0)}, f)
  rows = status.workdir_status(workdir)
  rows.append(dict(task="pick", encoder="objects", run_dir=done_eval, config=config,
                   **status.run_status(("evaluate",), done_eval, config)))
  status.estimate_left(rows)
  rows = {(r["task"], r["encoder"]): r for r in rows}
  eval_left = 360.0 / 3600
  assert rows[("push", "state")]["left"] == pytest.approx(700 * push_rate / 3600 + eval_left)
  assert rows[("pick", "state")]["left"] == pytest.approx(2000 * push_rate / 3600 + eval_left)
  # a pair of checkpoints that straddles the attempt's start (a stop between them) gives no pace
  os.utime(os.path.join(seed_1, "200"), (entry["attempt"] - 50.0,) * 2)
  assert status.pace(config, run, "train_policy", entry["attempt"], cores) is None
  rows = {(r["task"], r["encoder"]): r for r in status.workdir_status(workdir)}
  assert rows[("push", "state")]["left"] is None                          # its evaluation still has no rate


def test_an_unfinished_stage_says_how_far_its_seeds_and_rollouts_got(tmp_path):
  config = common.get_config("push", "savi", "tiny")
  config.pretrain.train_seeds, config.policy.train_seeds = (0, 1), (0, 1, 2)
  config.pretrain.train.steps, config.policy.train.steps = 40, 20
  config.eval.levels, config.eval.num_seeds, config.eval.rollouts_per_seed = ("train", "L1"), 1, 2
  run = str(tmp_path / "run")
  savi_dir = rundir.pretrain_dir(run, "savi")
  for stage_dir, step in ((rundir.seed_dir(savi_dir, 0), 40), (rundir.seed_dir(savi_dir, 1), 30),
                          (rundir.policy_dir(run, 0), 20), (rundir.policy_dir(run, 1), 10)):
    os.makedirs(os.path.join(rundir.checkpoints(stage_dir), str(step)))
    os.makedirs(os.path.join(rundir.checkpoints(stage_dir), f"{step + 10}.orbax-checkpoint-tmp-1"))  # half saved
  assert status.progress(config, run, "pretrain") == "seed 2/2 at 30/40"
  assert status.progress(config, run, "train_policy") == "seed 2/3 at 10/20"
  os.makedirs(rundir.eval_dir(run))
  for seed, rollouts in ((0, 4), (1, 1)):
    with open(rundir.rollout_log(run, seed), "w") as f:
      f.write("{}\n" * rollouts)
  assert status.progress(config, run, "evaluate") == "5/12 rollouts"     # 3 policies x 2 levels x 1 seed x 2
  assert status.progress(config, run, "cache") == ""
  rundir.record_stage(run, "train_policy", "running")                    # this process: alive
  assert status.run_status(("train_policy",), run, config)["stages"]["train_policy"] == "running (seed 2/3 at 10/20)"
  os.makedirs(os.path.join(rundir.checkpoints(rundir.policy_dir(run, 1)), "20"))
  os.makedirs(os.path.join(rundir.checkpoints(rundir.policy_dir(run, 2)), "20"))
  assert status.progress(config, run, "train_policy") == "all 3 seeds trained"


def test_status_command_prints_the_table_and_refuses_a_folder_without_a_run(tmp_path):
  _, workdir = _grid_workdir(tmp_path)
  env = dict(os.environ, JAX_PLATFORMS="cpu")
  out = subprocess.run([sys.executable, "-m", "roboshape.status", workdir], cwd=ROOT, env=env,
                       capture_output=True, text=True, check=False)
  assert out.returncode == 0, out.stderr
  assert "| push | state | pending |" in out.stdout and "4 pending of 4 run(s)" in out.stdout
  bad = subprocess.run([sys.executable, "-m", "roboshape.status", str(tmp_path / "nothing")], cwd=ROOT, env=env,
                       capture_output=True, text=True, check=False)
  assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "config.json not found" in bad.stderr


def _finished_run(tmp_path, encoder="savi"):
  config = common.get_config("push", encoder, "tiny")
  workdir = str(tmp_path / "run")
  rundir.save_config(config, workdir)
  rundir.record_stage(workdir, "collect", "done", 3.0)
  files = {os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_FILE): "{}",
           os.path.join(rundir.eval_dir(workdir), "results.csv"): "level,success\ntrain,1\n",
           os.path.join(rundir.eval_dir(workdir), "table.md"): "| table |",
           os.path.join(rundir.policy_dir(workdir), "val_metrics.json"): "[]",
           os.path.join(rundir.pretrain_dir(workdir, "savi"), "val_metrics.json"): "[1]",
           os.path.join(rundir.videos_dir(workdir), "train_s1_success.mp4"): "mp4",
           os.path.join(rundir.videos_dir(workdir), "train_s1_success.gif"): "gif"}
  for path, text in files.items():
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
      f.write(text)
  return config, workdir


def test_publish_copies_the_results_under_fixed_names_and_keeps_one_run(tmp_path):
  config, workdir = _finished_run(tmp_path)
  dest_root = str(tmp_path / "results")
  stale = os.path.join(dest_root, "push_savi", "videos", "L1_s9_failure.mp4")
  os.makedirs(os.path.dirname(stale))
  for path in (stale, os.path.join(dest_root, "push_savi", "README.md")):
    with open(path, "w") as f:
      f.write("earlier")
  dest = publish.publish(config, workdir, dest_root)
  assert dest == os.path.join(dest_root, "push_savi")
  found = sorted(os.path.relpath(os.path.join(d, n), dest) for d, _, names in os.walk(dest) for n in names)
  assert found == sorted(["README.md", "config.json", "stages.json", "results.csv", "table.md",
                          "policy_val_metrics.json", "savi_val_metrics.json",
                          os.path.join("videos", "train_s1_success.mp4")])
  with open(os.path.join(dest, "savi_val_metrics.json")) as f:
    assert f.read() == "[1]"
  with open(os.path.join(dest, "README.md")) as f:
    assert f.read() == "earlier"                          # a hand-written README stays
  with open(os.path.join(dest, "config.json")) as f:
    assert json.load(f)["encoder"] == "savi"
  publish.publish(config, workdir, dest_root)                # the same run again: its README stays
  assert os.path.isfile(os.path.join(dest, "README.md"))
  other = common.get_config("push", "savi", "tiny")          # another run into the same folder: the README that
  other.seed = config.seed + 1                               # described the one before goes with its files
  rundir.save_config(other, workdir)
  publish.publish(other, workdir, dest_root)
  assert not os.path.exists(os.path.join(dest, "README.md"))


def test_publish_from_the_command_line_and_its_one_line_refusals(tmp_path, capsys):
  config, workdir = _finished_run(tmp_path)
  dest_root = str(tmp_path / "results")
  assert publish.main(["publish", workdir, dest_root]) == 0
  dest = os.path.join(dest_root, "push_savi")
  assert capsys.readouterr().out.strip() == f"[roboshape] published {workdir} to {dest}"
  with open(os.path.join(dest, "config.json")) as f:
    assert json.load(f) == json.load(open(rundir.config_path(workdir)))
  grid = str(tmp_path / "grid")                          # a grid's workdir, a run not evaluated, bad usage
  grid_config = common.get_config("push", "state", "tiny")
  grid_config.grid = dict(tasks=("push",), encoders=("state",), publish="")
  rundir.save_config(grid_config, grid)
  os.remove(os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_FILE))
  for argv, message in (([grid, dest_root], "is a grid's workdir: publish each of its runs"),
                        ([workdir, dest_root], "has no evaluation results (results.json) to publish"),
                        ([workdir], "usage: python -m roboshape.report.publish RUN_WORKDIR DEST_ROOT")):
    assert publish.main(["publish"] + argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
  assert sorted(os.listdir(dest_root)) == ["push_savi"] and not os.path.exists(os.path.join(grid, "push_state"))


def test_publish_copies_every_training_seeds_validation_curve(tmp_path):
  config, workdir = _finished_run(tmp_path, "state")
  config.policy.train_seeds = (0, 3)
  for seed in (0, 3):
    path = os.path.join(rundir.policy_dir(workdir, seed), "val_metrics.json")
    os.makedirs(os.path.dirname(path))
    with open(path, "w") as f:
      f.write(f"[{seed}]")
  dest = publish.publish(config, workdir, str(tmp_path / "results"))
  assert not os.path.exists(os.path.join(dest, "policy_val_metrics.json"))   # policy/ is not a trained seed's
  for seed in (0, 3):
    with open(os.path.join(dest, f"policy_seed_{seed}_val_metrics.json")) as f:
      assert f.read() == f"[{seed}]"


def test_publish_takes_the_selected_pretraining_seeds_curve_and_last_figure(tmp_path):
  config, workdir = _finished_run(tmp_path)
  savi_dir = rundir.pretrain_dir(workdir, "savi")
  with open(rundir.selection_path(savi_dir), "w") as f:
    json.dump({"selected_seed": 1, "metric": "fg_ari", "seeds": [{"seed": 0}, {"seed": 1}]}, f)
  for seed in (0, 1):
    figures = os.path.join(rundir.seed_dir(savi_dir, seed), rundir.FIGURES_DIR)
    os.makedirs(figures)
    for step in (500, 8000, 10000):
      with open(os.path.join(figures, f"step_{step:07d}.png"), "w") as f:
        f.write(f"seed {seed} step {step}")
    with open(os.path.join(rundir.seed_dir(savi_dir, seed), "val_metrics.json"), "w") as f:
      f.write(f"[{seed}]")
  dest = publish.publish(config, workdir, str(tmp_path / "results"))
  with open(os.path.join(dest, "savi_selected_step_0010000.png")) as f:
    assert f.read() == "seed 1 step 10000"
  with open(os.path.join(dest, "savi_selected_val_metrics.json")) as f:
    assert f.read() == "[1]"
  assert sorted(n for n in os.listdir(dest) if n.startswith("savi_")) == [
      "savi_selected.json", "savi_selected_step_0010000.png", "savi_selected_val_metrics.json",
      "savi_val_metrics.json"]


def test_publish_refuses_a_run_without_evaluation_results_and_writes_nothing(tmp_path):
  config, workdir = _finished_run(tmp_path, "state")
  os.remove(os.path.join(rundir.eval_dir(workdir), rundir.RESULTS_FILE))
  with pytest.raises(UserError, match="no evaluation results"):
    publish.publish(config, workdir, str(tmp_path / "results"))
  assert not os.path.exists(tmp_path / "results")


def test_publish_records_the_dataset_and_takes_the_encoder_files_of_the_run_that_pretrained_it(tmp_path):
  import shutil  # pylint: disable=import-outside-toplevel
  from roboshape import data as data_lib  # pylint: disable=import-outside-toplevel
  config, workdir = _finished_run(tmp_path)
  # The plain run has no dataset.json of its own (collected before runs recorded one): made from its roboshape.json.
  state = {"name": "roboshape_push", "complete": True, "env_version": "v",
           "splits": {"train": {"shards": [{"sha256": "ab", "seeds": [0, 2]}]},
                      "val": {"shards": [{"sha256": "cd", "seeds": [1000000]}]}}}
  dataset = data_lib.dataset_path(config, workdir)
  os.makedirs(dataset)
  with open(os.path.join(dataset, data_lib.STATE_FILE), "w") as f:
    json.dump(state, f)
  root = str(tmp_path / "results")
  with open(os.path.join(publish.publish(config, workdir, root), "dataset.json")) as f:
    assert json.load(f) == dict(identity=data_lib.identity(state), name="roboshape_push", complete=True,
                                env_version="v", episodes={"train": 2, "val": 1}, shards={"train": 1, "val": 1})
  # A +proprio run serving that run's SAVi: its own folder, its own dataset.json, the SAVi's curve from the other run.
  proprio = common.get_config("push", "savi+proprio", "tiny")
  proprio.pretrain.from_workdir = workdir
  other = str(tmp_path / "proprio")
  shutil.copytree(workdir, other, ignore=shutil.ignore_patterns("savi", "data"))
  own = {"identity": data_lib.identity(state), "name": "its own record"}
  with open(rundir.dataset_record(other), "w") as f:
    json.dump(own, f)
  dest = publish.publish(proprio, other, root)
  assert dest == os.path.join(root, "push_savi+proprio")
  with open(os.path.join(dest, "savi_val_metrics.json")) as f:
    assert f.read() == "[1]"
  with open(os.path.join(dest, "dataset.json")) as f:
    assert json.load(f) == own


def test_publish_refuses_a_cell_on_another_dataset_than_its_published_row_and_the_grid_goes_on(tmp_path, capsys):
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  config, workdir = _finished_run(tmp_path, "state")
  root = str(tmp_path / "results")
  with open(rundir.dataset_record(workdir), "w") as f:
    json.dump({"identity": "aaaa"}, f)
  publish.publish(config, workdir, root)                                  # push x state on dataset aaaa
  pick = common.get_config("pick", "state", "tiny")                       # another task's row: not compared
  with open(rundir.config_path(workdir), "w") as f:
    f.write(pick.to_json())
  publish.publish(pick, workdir, root)
  with open(rundir.config_path(workdir), "w") as f:
    f.write(config.to_json())
  savi, other = _finished_run(tmp_path / "second")
  with open(rundir.dataset_record(other), "w") as f:
    json.dump({"identity": "bbbb"}, f)
  before = sorted(os.listdir(root))
  with pytest.raises(UserError, match=r"push x savi was trained on dataset bbbb, but the push cells in .* on "
                                      r"another \(push_state on aaaa\): publish this row into another folder"):
    publish.publish(savi, other, root)
  assert sorted(os.listdir(root)) == before == ["pick_state", "push_state"]
  # The grid says so in one line and goes on; the same run on the row's dataset is published.
  grid = common.get_config("push", "state", "tiny")
  grid.grid = dict(tasks=("push",), encoders=("savi",), publish=root)
  stages._finish_run(grid, "push", "savi", savi, other, None)   # pylint: disable=protected-access
  assert "[roboshape] not published: push x savi was trained on dataset bbbb" in capsys.readouterr().out
  assert not os.path.exists(os.path.join(root, "push_savi"))
  with open(rundir.dataset_record(other), "w") as f:
    json.dump({"identity": "aaaa"}, f)
  stages._finish_run(grid, "push", "savi", savi, other, None)   # pylint: disable=protected-access
  assert "[roboshape] published push x savi" in capsys.readouterr().out
  with pytest.raises(UserError, match="is damaged"):                      # a damaged record of the row: one line
    with open(os.path.join(root, "push_state", "dataset.json"), "w") as f:
      f.write("{")
    publish.publish(savi, other, root)
