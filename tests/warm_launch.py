"""launch.py kept warm, for the tests that run it as a command many times (tests/test_config_check.py).

Each run of launch.py as a fresh process imports JAX and Flax before its config check reaches the policy's ranges,
which costs more than the check. `WarmLaunch` starts one server process that imports once what launch.py and the
check import; for each run it forks a child that executes launch.py as `__main__` (runpy) with that run's argv,
its stdout and stderr in files, and reports the child's exit status: the same code path, exit status and output
as `python launch.py ...`, without the interpreter's start-up and imports.

  with WarmLaunch(cwd=ROOT) as launch:
    out = launch.run(["--config=configs/pick_savi.py:tiny", ...])   # a subprocess.CompletedProcess
"""
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile

# The server: warms the imports, then forks a child per request line ({"argv", "out", "err"}), answers its status.
_SERVER = r"""
import json, os, runpy, sys, traceback
sys.argv = ["launch.py"]
sys.path.insert(0, os.getcwd())
from absl import app, flags, logging                      # launch.py's imports
from ml_collections import config_flags
from roboshape import cli, stages
from configs import common
stages.check(common.get_config("pick", "savi", "tiny"))  # imports the owners of every section's ranges
print("ready", flush=True)
for line in sys.stdin:
  request = json.loads(line)
  pid = os.fork()
  if pid == 0:
    code = 1
    try:
      for fd, path in ((1, request["out"]), (2, request["err"])):
        os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), fd)
      os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
      sys.argv = ["launch.py", *request["argv"]]
      runpy.run_path("launch.py", run_name="__main__")
      code = 0
    except SystemExit as e:
      code = 0 if e.code is None else (e.code if isinstance(e.code, int) else 1)
    except BaseException:  # what a fresh process would print and exit with
      traceback.print_exc()
    finally:
      sys.stdout.flush()
      sys.stderr.flush()
      os._exit(code)
  _, status = os.waitpid(pid, 0)
  print(json.dumps(os.waitstatus_to_exitcode(status)), flush=True)
"""


class WarmLaunch:
  """One warm launch.py server (see the module's docstring); `run` one command at a time, `close` when done."""

  def __init__(self, cwd, env=None):
    self._dir = tempfile.mkdtemp(prefix="warm_launch_")
    self._proc = subprocess.Popen([sys.executable, "-c", _SERVER], cwd=cwd, env=env, stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, start_new_session=True)
    ready = self._answer(120)
    assert ready == "ready", ready

  def _answer(self, timeout):
    """The server's next line; kills the server and its child when none comes within `timeout` seconds."""
    if not select.select([self._proc.stdout], [], [], timeout)[0]:
      self.close()
      raise TimeoutError(f"launch.py did not finish within {timeout} s")
    return self._proc.stdout.readline().strip()

  def run(self, argv, timeout=60):
    """launch.py with `argv` (its arguments, without the program's name): a subprocess.CompletedProcess."""
    out, err = os.path.join(self._dir, "stdout"), os.path.join(self._dir, "stderr")
    self._proc.stdin.write(json.dumps({"argv": list(argv), "out": out, "err": err}) + "\n")
    self._proc.stdin.flush()
    code = json.loads(self._answer(timeout))
    with open(out) as f_out, open(err) as f_err:
      return subprocess.CompletedProcess(["launch.py", *argv], code, f_out.read(), f_err.read())

  def close(self):
    if self._proc.poll() is None:
      os.killpg(self._proc.pid, signal.SIGKILL)
      self._proc.wait()
    self._proc.stdin.close()
    self._proc.stdout.close()
    shutil.rmtree(self._dir, ignore_errors=True)   # once: a timeout closes before the fixture does

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()
