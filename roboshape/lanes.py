"""A grid's runs in parallel lanes: up to `grid.lanes` runs at once, each a child process pinned to its own cores.

Why lanes: on a 2-core CPU two runs pinned one per core do at least the work of one run spread over both cores (the
`:small` behaviour-cloning and SAVi steps scale less than linearly with cores, even with the cores as JAX devices,
roboshape/cli.py; the step times on both 2-core machines: results/small/README.md), and lanes also overlap stages
that use the cores badly (collection's resets, evaluation). `configs/reproduce.py:small` therefore runs two lanes;
each lane's child makes its own cores its devices.

  run_parallel(run, jobs, lanes, on_done)   # jobs: (name, config, run_dir); on_done(job, exit code, last line)

Each job is a child `python -m roboshape.lanes RUN_DIR CORES PARENT_PID`, which pins itself to CORES
(`child_setup`), reads `run` and its config (pickled) on stdin and calls `run(config, RUN_DIR)`. `run` is a
module-level function, pickled by name: the child imports its module when it unpickles it, so this module imports
none of its callers. A grid passes `roboshape.stages.run`, so each run resumes and fails exactly as `launch.py`
would; everything it prints goes to RUN_DIR/log.txt (appended across resumes). Lane i owns the cores cores[i::lanes]
of this process's affinity, and a job's simulator workers inherit them. Ctrl-C or SIGTERM here sends SIGTERM to
every child (each stops the way an interrupted run stops and resumes the same way) and re-raises here; a parent
that dies any other way (SIGKILL) takes its children with it (`child_setup`). Each child holds its run's workdir
(rundir.hold_workdir), so a second grid on the same runs stops in one line instead of running them twice. When
no run is pending and one is left running, it is stopped and resumed on every core (`_widen`): a grid's last run
does not leave the other lanes' cores idle.
"""
import ctypes
import os
import pickle
import signal
import subprocess
import sys
import time
from typing import Any, Callable, List, Mapping, Optional, Sequence, Set, Tuple

from roboshape import errors
from roboshape import fileio
from roboshape.errors import UserError

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_PR_SET_PDEATHSIG = 1   # linux/prctl.h
LOG_FILE = "log.txt"
# how a child stopped by SIGTERM exits: 143 from a run (cli.interrupt_code), killed by it before its handlers were in
# place, or killed 60 s on (`_interrupt`)
_STOPPED = (128 + signal.SIGTERM, -signal.SIGTERM, -signal.SIGKILL)
Job = Tuple[str, Any, str]        # (name, config, run_dir)
Run = Callable[[Any, str], None]  # run(config, run_dir): a module-level function, so it pickles by name


def lane_cores(lanes: int) -> List[Set[int]]:
  """The cores of each lane: this process's cores dealt round-robin, at most one lane per core."""
  cores = sorted(os.sched_getaffinity(0))
  lanes = max(1, min(int(lanes), len(cores)))
  return [set(cores[i::lanes]) for i in range(lanes)]


def last_line(path: str) -> str:
  """The last non-empty line of a log (a failed child's one-line error), or "" without one."""
  try:
    lines = fileio.tail_lines(path)
  except OSError:
    return ""
  return lines[-1].strip() if lines else ""


def child_setup(cores: Set[int], parent: int) -> None:
  """Runs first in a lane's child (`main`, before it imports JAX): pins it to `cores`, and asks Linux to send it
  SIGTERM when the process that started it exits (prctl PR_SET_PDEATHSIG), so a lane never outlives its grid: a
  parent killed even by SIGKILL takes its lanes with it, each stopping as an interrupted run stops. A child whose
  parent is already gone (it died before the prctl) exits at once. In the child rather than in Popen's preexec_fn:
  Python code run between fork and exec can deadlock when the parent holds JAX's threads."""
  os.sched_setaffinity(0, cores)
  libc = ctypes.CDLL(None, use_errno=True)
  if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
    raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
  if os.getppid() != parent:
    os._exit(128 + signal.SIGTERM)  # pylint: disable=protected-access


def _start(run: Run, job: Job, cores: Set[int]) -> subprocess.Popen:
  _, config, run_dir = job
  os.makedirs(run_dir, exist_ok=True)
  env = dict(os.environ)
  env["PYTHONPATH"] = _ROOT + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
  with open(os.path.join(run_dir, LOG_FILE), "ab") as log:
    child = subprocess.Popen([sys.executable, "-m", "roboshape.lanes", run_dir, ",".join(map(str, sorted(cores))),
                              str(os.getpid())], stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT, env=env)
  child.stdin.write(pickle.dumps((run, config)))
  child.stdin.close()
  return child


def _interrupt(children) -> None:
  """SIGTERM to every child (each stops as an interrupted run does, cli.Terminated), then a kill for any still alive
  after 60 s. SIGTERM, not SIGINT: a grid started as a background job (`nohup ... &`) ignores SIGINT, and so do the
  children it starts; a child deaf to the signal would be killed without saving the steps it trained."""
  for child in children:
    if child.poll() is None:
      child.send_signal(signal.SIGTERM)
  deadline = time.time() + 60
  for child in children:
    try:
      child.wait(timeout=max(0.1, deadline - time.time()))
    except subprocess.TimeoutExpired:
      child.kill()
      child.wait()


def next_job(pending: Sequence[Job], running_dirs: Set[str], after: Mapping[str, str]) -> Optional[int]:
  """The index in `pending` of the first job that may start: one whose run_dir `after` maps to no run_dir among
  the jobs pending or running (`running_dirs`). None when every pending job waits; with nothing running, the first
  pending job all the same (what it waits for is not among the jobs left, so it never comes)."""
  unfinished = set(running_dirs) | {job[2] for job in pending}
  for i, job in enumerate(pending):
    if after.get(job[2]) not in unfinished:
      return i
  return 0 if pending and not running_dirs else None


def run_parallel(run: Run, jobs: Sequence[Job], lanes: int, on_done: Callable[[Job, int, str], None],
                 poll_seconds: float = 2.0, after: Optional[Mapping[str, str]] = None,
                 widen_last: bool = True) -> None:
  """Runs `run(config, run_dir)` of each job in its own child, in order, up to `lanes` at once, one lane per share of
  the cores (`lane_cores`); calls `on_done(job, exit code, last line of its log)` as each one ends (exit code 2: a
  one-line UserError). `after` maps a job's run_dir to the run_dir of a job it waits for (a run that serves another
  run's pretrained encoder): it starts once that one has ended, and the jobs behind it may start before it
  (`next_job`). With `widen_last`, the last run left gets the cores no other run is left to use (`_widen`)."""
  free = lane_cores(lanes)
  pending = list(jobs)
  running = []      # (job, child, cores, start)
  try:
    while pending or running:
      while pending and free:
        index = next_job(pending, {e[0][2] for e in running}, after or {})
        if index is None:
          break
        job = pending.pop(index)
        if widen_last and not pending and not running:    # the last run, and no other: every free core
          cores, free = set().union(*free), []
        else:
          cores = free.pop(0)
        print(f"[roboshape] lane on cores {sorted(cores)}: {job[0]} -> {job[2]} (log: "
              f"{os.path.join(job[2], LOG_FILE)})", flush=True)
        running.append((job, _start(run, job, cores), cores, time.time()))
      time.sleep(poll_seconds)
      for entry in [e for e in running if e[1].poll() is not None]:
        job, child, cores, start = entry
        running.remove(entry)
        free.append(cores)
        line = last_line(os.path.join(job[2], LOG_FILE))
        print(f"[roboshape] {job[0]} ended in {time.time() - start:.0f}s with status {child.returncode}"
              + ("" if child.returncode == 0 else f": {line}"), flush=True)
        on_done(job, child.returncode, line)
      if widen_last and not pending and free and len(running) == 1:
        _widen(run, running, free)
  except BaseException:
    _interrupt([child for _, child, _, _ in running])
    raise


def _widen(run: Run, running: list, free: List[Set[int]]) -> None:
  """The one run still going while no run is pending: stops it (SIGTERM, so it saves its steps as an interrupted run
  does) and starts it again on its own cores and every free one, where it resumes with one JAX device per core.
  Why: a grid's last run is often its longest (a pretraining run of place), and on one core of two it would leave
  the other idle for hours; what the stop costs is the child's start (JAX, its data) once more. A child that ended
  by itself before the signal reached it stays in `running`, reported as any ended child is."""
  job, child, cores, start = running[0]
  wider = set(cores).union(*free)
  print(f"[roboshape] {job[0]} is the last run left: it stops and resumes on cores {sorted(wider)}", flush=True)
  _interrupt([child])
  if child.returncode in _STOPPED:
    free.clear()
    running[0] = (job, _start(run, job, wider), wider, start)


def main(argv) -> int:
  """The child: `python -m roboshape.lanes RUN_DIR CORES PARENT_PID`, (run, config) pickled on stdin."""
  if len(argv) != 4:
    print("usage: python -m roboshape.lanes RUN_DIR CORES PARENT_PID < pickled (run, config) (started by "
          "roboshape.lanes.run_parallel)", file=sys.stderr)
    return 2
  from roboshape import cli  # pylint: disable=import-outside-toplevel
  child_setup({int(c) for c in argv[2].split(",")}, int(argv[3]))
  devices = cli.host_device_per_core(override=True)   # this lane's cores (pinned just now), before JAX starts
  run, config = pickle.load(sys.stdin.buffer)     # imports run's module (roboshape.stages for a grid)
  print(f"[roboshape] {config.name} on cores {sorted(os.sched_getaffinity(0))} ({devices} JAX CPU device(s)), pid "
        f"{os.getpid()}", flush=True)
  try:
    run(config, argv[1])
  except UserError as e:
    return errors.print_error(e)
  except KeyboardInterrupt as e:
    print(f"roboshape: {cli.INTERRUPTED}", file=sys.stderr, flush=True)
    return cli.interrupt_code(e)
  return 0


if __name__ == "__main__":
  from roboshape import cli  # pylint: disable=ungrouped-imports
  # SIGTERM (from its grid, its parent's death, or a kill) stops it as Ctrl-C would, and a second one while it saves
  # its steps does not break that off (`_interrupt` kills it 60 s on)
  cli.install_signal_handlers(hurry=(signal.SIGINT,))
  cli.exit_process(main(sys.argv))
