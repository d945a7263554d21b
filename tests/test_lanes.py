"""Grid runs in parallel lanes (roboshape/lanes.py): child processes pinned to disjoint cores, their exit codes and
one-line errors, and the grid's skip / fail rules applied to them."""
import json
import os

import pytest

from configs import common
from configs import reproduce
from roboshape import lanes
from roboshape import rundir
from roboshape import stages
from roboshape.report import publish
from roboshape.errors import UserError


def test_lane_cores_deal_this_process_cores_once_each():
  cores = sorted(os.sched_getaffinity(0))
  for n in (1, 2, 99):
    dealt = lanes.lane_cores(n)
    assert len(dealt) == min(n, len(cores)) and all(dealt)
    assert sorted(c for lane in dealt for c in lane) == cores


def test_a_run_that_serves_another_runs_encoder_waits_for_it_and_the_runs_behind_it_go_first():
  jobs = [(name, None, f"/w/{name}") for name in ("savi", "ae", "savi+proprio", "ae+proprio", "state")]
  after = {"/w/savi+proprio": "/w/savi", "/w/ae+proprio": "/w/ae"}
  assert lanes.next_job(jobs, set(), after) == 0
  assert lanes.next_job(jobs[2:], {"/w/savi"}, after) == 1          # ae ended: ae+proprio before savi+proprio
  assert lanes.next_job(jobs[2:3], {"/w/savi"}, after) is None      # savi+proprio waits while savi runs
  assert lanes.next_job(jobs[2:3], set(), after) == 0               # and starts once it has ended
  assert lanes.next_job(jobs[2:4], set(), {"/w/savi+proprio": "/w/ae+proprio", "/w/ae+proprio": "/w/savi+proprio"}
                        ) == 0                                      # a circle of waits never stalls the grid


def test_children_run_pinned_and_report_their_exit_codes(tmp_path):
  jobs = []
  for name in ("a", "bad"):
    config = common.get_config("push", "state", "tiny")
    config.stages = ()              # the child checks the config and the workdir, and saves config.json
    if name == "bad":
      config.eval.levels = ("L9",)
    jobs.append((name, config, str(tmp_path / name)))
  ended = {}
  lanes.run_parallel(stages.run, jobs, 2, lambda job, code, line: ended.update({job[0]: (code, line)}),
                     poll_seconds=0.2, widen_last=False)
  assert ended["a"][0] == 0
  assert ended["bad"][0] == 2 and ended["bad"][1].startswith("roboshape: error: eval.levels")
  assert json.load(open(tmp_path / "a" / "config.json"))["encoder"] == "state"
  assert not (tmp_path / "bad" / "config.json").exists()          # bad input writes nothing but the log
  pinned = {}
  for name in ("a", "bad"):
    line = next(l for l in open(tmp_path / name / lanes.LOG_FILE) if " on cores " in l)
    pinned[name] = line.split(" on cores ")[1].split("]")[0]
    cores = len(pinned[name].strip("[").split(","))
    assert f"({cores} JAX CPU device(s))" in line                 # one device per core it was pinned to
  if len(os.sched_getaffinity(0)) >= 2:                            # they ran at once, each on its own core
    assert pinned["a"] != pinned["bad"] and "," not in pinned["a"] + pinned["bad"]


def test_a_grid_in_lanes_skips_a_failed_baseline_and_stops_for_savi(tmp_path):
  config = reproduce.get_config("tiny")
  config.grid.encoders, config.grid.lanes, config.stages = ("savi", "r3m"), 2, ("cache",)
  config.grid.publish = str(tmp_path / "published")
  config.baselines.r3m.path = str(tmp_path / "model.pt")      # a file: the run starts in its lane, and fails there
  (tmp_path / "model.pt").write_bytes(b"")
  with pytest.raises(UserError, match=r"grid runs failed: push x savi \(.+\).*log\.txt"):
    stages.run(config, str(tmp_path / "grid"))    # no dataset: each run's cache stage fails with one line
  reason = json.load(open(tmp_path / "grid" / "push_r3m" / "SKIPPED.json"))["reason"]
  assert reason and "\n" not in reason and not reason.startswith("roboshape: error")
  assert not (tmp_path / "grid" / "push_savi" / "SKIPPED.json").exists()
  assert publish.grid_record(config.grid.publish) == dict(tasks=["push"], columns=["savi", "r3m"],
                                                          skipped={"push_r3m": reason})
  clock = rundir.read_stage_log(str(tmp_path / "grid"))[rundir.GRID_CLOCK]    # the grid's own attempt, logged
  assert clock["state"] == "running" and clock["pid"] == os.getpid() and clock["beat"] > clock["attempt"]


def _wait_for(predicate, seconds: float = 20.0) -> bool:
  import time  # pylint: disable=import-outside-toplevel
  deadline = time.time() + seconds
  while time.time() < deadline:
    if predicate():
      return True
    time.sleep(0.1)
  return False


def _gone(pid: int) -> bool:
  """True once `pid` has exited (a zombie no one has reaped yet counts as exited)."""
  try:
    with open(f"/proc/{pid}/stat") as f:
      return f.read().rsplit(")", 1)[1].split()[0] == "Z"
  except FileNotFoundError:
    return True


def test_a_second_run_on_a_held_workdir_stops_in_one_line_and_a_killed_holder_frees_it(tmp_path):
  import signal  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  from roboshape import rundir  # pylint: disable=import-outside-toplevel
  workdir = str(tmp_path / "run")
  holder = subprocess.Popen(
      [sys.executable, "-c", "import sys, time\nfrom roboshape import rundir\n"
       "with rundir.hold_workdir(sys.argv[1]):\n  print('held', flush=True)\n  time.sleep(120)\n", workdir],
      stdout=subprocess.PIPE, text=True, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  try:
    assert holder.stdout.readline().strip() == "held"
    config = common.get_config("push", "state", "tiny")
    config.stages = ()
    with pytest.raises(UserError, match=rf"is in use by another run \(pid {holder.pid}\): wait for it") as e:
      stages.run(config, workdir)
    assert "\n" not in str(e.value)
    assert sorted(os.listdir(workdir)) == [rundir.RUN_LOCK]          # nothing written: no config.json
  finally:
    holder.send_signal(signal.SIGKILL)
    holder.wait()
  stages.run(config, workdir)                                          # the OS released the dead holder's lock
  assert json.load(open(os.path.join(workdir, "config.json")))["encoder"] == "state"
  with rundir.hold_workdir(workdir):                                   # and the finished run released its own
    pass


def test_a_lane_child_dies_with_its_parent_even_when_the_parent_is_killed(tmp_path):
  import signal  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  script = ("import os, subprocess, sys, time\n"       # the child sets itself up first, as lanes.main does
            "child = subprocess.Popen([sys.executable, '-c', 'import time; from roboshape import lanes; '\n"
            "    f'lanes.child_setup({{0}}, {os.getpid()}); time.sleep(120)'])\n"
            "print(child.pid, flush=True)\ntime.sleep(120)\n")
  parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
  child = int(parent.stdout.readline())
  assert not _gone(child)

  def allowed():
    with open(f"/proc/{child}/status") as f:
      return next(l for l in f if l.startswith("Cpus_allowed_list")).split()[1]
  assert _wait_for(lambda: allowed() == "0"), allowed()            # it pins itself as asked
  parent.send_signal(signal.SIGKILL)
  parent.wait()
  assert _wait_for(lambda: _gone(child)), f"lane child {child} outlived its killed parent"


def wait_to_be_interrupted(config, run_dir: str) -> None:
  """A lane's run (module-level: a child unpickles it by name) that says it started, then waits until an interrupt
  reaches it, and notes that it did, as a training stage saves its steps when interrupted."""
  import time  # pylint: disable=import-outside-toplevel
  del config
  try:                                 # the note inside: an interrupt that comes as it is written still counts
    open(os.path.join(run_dir, "started"), "w").close()
    time.sleep(120)
  except KeyboardInterrupt:
    time.sleep(1.0)                    # saving: a second signal now must not break it off
    open(os.path.join(run_dir, "interrupted"), "w").close()
    raise


@pytest.mark.parametrize("whole_group", [False, True])
def test_a_grid_in_the_background_stops_its_lanes_as_interrupted_runs(tmp_path, whole_group):
  """A grid started as a background job (`nohup ... &`: SIGINT ignored, inherited by its lanes) and stopped with
  SIGTERM stops each lane the way an interrupted run stops (a training stage saves its steps), not by a kill; also
  when the SIGTERM goes to the whole process group, so that each lane gets it twice (from the kill and its grid)."""
  import signal  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  here = os.path.dirname(os.path.abspath(__file__))
  run_dir = str(tmp_path / "a")
  script = ("import signal, sys\nimport ml_collections\nfrom roboshape import cli, lanes\nimport test_lanes\n"
            "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"          # as a background job: its lanes inherit it
            "cli.install_signal_handlers()\ntry:\n"
            "  lanes.run_parallel(test_lanes.wait_to_be_interrupted, [('a', ml_collections.ConfigDict({'name': 'a'}), "
            "sys.argv[1])], 1, lambda *a: None, poll_seconds=0.2)\n"
            "except KeyboardInterrupt as e:\n  sys.exit(cli.interrupt_code(e))\n")
  env = dict(os.environ, PYTHONPATH=here + os.pathsep + os.environ.get("PYTHONPATH", ""))
  grid = subprocess.Popen([sys.executable, "-c", script, run_dir], cwd=os.path.dirname(here), env=env,
                          start_new_session=True)
  try:
    assert _wait_for(lambda: os.path.exists(os.path.join(run_dir, "started")), 60.0), "the lane never started"
    if whole_group:
      os.killpg(grid.pid, signal.SIGTERM)
    else:
      grid.send_signal(signal.SIGTERM)
    assert grid.wait(timeout=90) == 128 + signal.SIGTERM
  finally:
    grid.kill()
  log = open(os.path.join(run_dir, lanes.LOG_FILE)).read()
  assert os.path.exists(os.path.join(run_dir, "interrupted")), log           # the interrupt reached the run
  assert log.rstrip().endswith("roboshape: interrupted; run the same command to resume")


def note_cores(config, run_dir: str) -> None:
  """A lane's run that appends how many cores it holds to <run_dir>/cores.txt; on one core with `config.hold` it
  then waits to be interrupted, and with `config.wait_for` it returns once that file exists."""
  import time  # pylint: disable=import-outside-toplevel
  with open(os.path.join(run_dir, "cores.txt"), "a") as f:
    f.write(f"{len(os.sched_getaffinity(0))}\n")
  deadline = time.time() + 120
  while config.wait_for and not os.path.exists(config.wait_for) and time.time() < deadline:
    time.sleep(0.05)
  if config.hold and len(os.sched_getaffinity(0)) == 1:
    time.sleep(120)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two cores")
def test_the_last_run_left_resumes_on_the_cores_the_other_lanes_left(tmp_path, monkeypatch, capsys):
  import ml_collections  # pylint: disable=import-outside-toplevel
  here = os.path.dirname(os.path.abspath(__file__))
  monkeypatch.setenv("PYTHONPATH", here + os.pathsep + os.environ.get("PYTHONPATH", ""))  # children unpickle
  long_dir, short_dir, alone_dir = (str(tmp_path / name) for name in ("long", "short", "alone"))
  jobs = [("long", ml_collections.ConfigDict(dict(name="long", hold=True, wait_for="")), long_dir),
          ("short", ml_collections.ConfigDict(dict(name="short", hold=False,
                                                   wait_for=os.path.join(long_dir, "cores.txt"))), short_dir)]
  ended = []
  lanes.run_parallel(note_cores, jobs, 2, lambda job, code, line: ended.append((job[0], code)), poll_seconds=0.2)
  assert ended == [("short", 0), ("long", 0)]                  # the stop in between is no end of the run
  n = len(os.sched_getaffinity(0))
  assert open(os.path.join(short_dir, "cores.txt")).read().split() == ["1"]
  assert open(os.path.join(long_dir, "cores.txt")).read().split() == ["1", str(n)]   # stopped, resumed on all
  assert f"long is the last run left: it stops and resumes on cores {sorted(os.sched_getaffinity(0))}" in (
      capsys.readouterr().out)
  lanes.run_parallel(note_cores, [("alone", jobs[0][1], alone_dir)], 2, lambda *a: None, poll_seconds=0.2)
  assert open(os.path.join(alone_dir, "cores.txt")).read().split() == [str(n)]       # alone: every core at once
  lanes.run_parallel(note_cores, jobs[1:], 2, lambda *a: None, poll_seconds=0.2, widen_last=False)
  assert open(os.path.join(short_dir, "cores.txt")).read().split() == ["1", "1"]     # unless asked not to
