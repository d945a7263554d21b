"""Command-line plumbing shared by launch.py and the tools: one-line errors instead of tracebacks.

A `roboshape.errors.UserError` (bad input: a missing file, an unknown task, a dataset of another config) says what
to do; the command prints it as one line and exits with status 2, no traceback.

Ctrl-C (SIGINT) and SIGTERM end a run with one line, `roboshape: interrupted; run the same command to resume`, and
exit status 130 / 143 (`run_app`, then `exit_process`): the signal raises in the main thread, so each stage's
`with` blocks close what they hold (the checkpoint writer finishes the checkpoint in flight, simulator workers are
shut down); a second signal while that happens exits at once (every stage resumes after a kill as well), except a
second SIGTERM in a grid's lane (roboshape/lanes.py: its grid sends it one when stopped, which a kill of the whole
process group doubles; the grid kills a lane still alive 60 s later).
"""
import difflib
import logging
import os
import signal
import sys
import threading
from typing import Callable, Sequence

from absl import app
from absl import flags

from roboshape import errors
from roboshape import rundir
from roboshape.errors import UserError


INTERRUPTED = "interrupted; run the same command to resume"
INTERRUPT_CODES = (128 + signal.SIGINT, 128 + signal.SIGTERM)


class Terminated(KeyboardInterrupt):
  """SIGTERM, raised in the main thread like Ctrl-C's KeyboardInterrupt (so everything that cleans up after one
  cleans up after the other)."""


def interrupt_code(e: KeyboardInterrupt) -> int:
  """The exit status of a run that `e` interrupted: 143 for SIGTERM, 130 for Ctrl-C."""
  return 128 + (signal.SIGTERM if isinstance(e, Terminated) else signal.SIGINT)


def _on_signal(signum, frame) -> None:
  """The first SIGINT/SIGTERM raises in the main thread; a second one of `install_signal_handlers`' `hurry`, while
  the first is cleaned up, exits now (another second one is let be)."""
  del frame
  if getattr(_on_signal, "seen", False):
    if signum not in getattr(_on_signal, "hurry", ()):
      return
    print(f"roboshape: {INTERRUPTED}", file=sys.stderr, flush=True)
    os._exit(128 + signum)  # pylint: disable=protected-access
  _on_signal.seen = True
  _quiet_after_interrupt()   # orbax logs the save it breaks off as it re-raises, before any `except` sees it
  raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def install_signal_handlers(hurry=(signal.SIGINT, signal.SIGTERM)):
  """Routes SIGINT and SIGTERM to `_on_signal` (main thread only); returns the previous handlers. A second signal
  of `hurry` exits at once (a person pressing Ctrl-C again); a grid's lane passes SIGINT alone, since the one stop
  of a grid can reach it twice as SIGTERM (the grid's own, and a kill of the whole process group or session)."""
  if threading.current_thread() is not threading.main_thread():
    return {}
  _on_signal.seen, _on_signal.hurry = False, tuple(hurry)
  previous = {}
  for signum in (signal.SIGINT, signal.SIGTERM):
    if signal.getsignal(signum) is not signal.SIG_IGN:   # a background job keeps ignoring Ctrl-C
      previous[signum] = signal.signal(signum, _on_signal)
  return previous


def _quiet_after_interrupt() -> None:
  """Silences what background threads (orbax's checkpoint writer, tf.data) log or raise after an interrupt: the one
  line `run_app` prints says what happened."""
  logging.disable(logging.CRITICAL)
  threading.excepthook = lambda args: None


def _flat_keys(config, prefix=""):
  for key, value in config.items():
    path = f"{prefix}{key}"
    if hasattr(value, "items"):
      yield from _flat_keys(value, path + ".")
    else:
      yield path


def _root_cause(e: BaseException) -> str:
  while e.__cause__ is not None or e.__context__ is not None:
    e = e.__cause__ or e.__context__
  text = str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)
  return text.strip().splitlines()[0] if text.strip() else type(e).__name__


def _check_overrides(argv: Sequence[str]) -> None:
  """Parses the flags; a bad config file or an unknown --config.x.y fails with one clear line (naming the new key of
  a moved one, rundir.RENAMED, or why a removed one left, rundir.REMOVED)."""
  config_args = [a for a in argv[1:] if a.startswith("--config=")]
  if config_args and "config" in flags.FLAGS:
    spec = config_args[-1].split("=", 1)[1]
    path = spec.split(":", 1)[0]
    if not os.path.isfile(path):
      raise UserError(f"config file {path!r} not found; experiments live in configs/, e.g. configs/pick_savi.py:tiny")
    try:
      config = flags.FLAGS["config"].parser.parse(spec)
    except Exception as e:  # pylint: disable=broad-except
      raise UserError(f"cannot load --config={spec}: {_root_cause(e)}") from None
    keys = set(_flat_keys(config))
    prefixes = {k.rsplit(".", i)[0] for k in keys for i in range(k.count(".") + 1)}
    for arg in argv[1:]:
      if not arg.startswith("--config."):
        continue
      key = arg.split("=", 1)[0][len("--config."):]
      if key in prefixes:
        continue
      if key in rundir.REMOVED:
        raise UserError(f"config key {key!r} was removed: {rundir.REMOVED[key][1]}; drop --config.{key}")
      if key in rundir.RENAMED:
        raise UserError(f"config key {key!r} is now {rundir.RENAMED[key]!r} (the pretrain section, shared by every "
                        f"pretrained encoder): use --config.{rundir.RENAMED[key]}=...")
      near = difflib.get_close_matches(key, sorted(keys), n=4, cutoff=0.6)
      if not near:
        section = key.split(".")[0]
        near = sorted(k for k in keys if k.split(".")[0] == section)[:8] or sorted(k for k in keys if "." not in k)
      raise UserError(f"unknown config key {key!r}; valid keys near it: {', '.join(near)}")
  try:
    flags.FLAGS(argv)
  except Exception as e:  # pylint: disable=broad-except
    raise UserError(f"bad command-line flag: {_root_cause(e)}") from None


HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"


def host_device_per_core(override: bool = False) -> int:
  """Makes JAX's CPU platform one device per core of this process (XLA_FLAGS), so the train loops split each batch
  over the cores (roboshape/train/sharding.py); returns the count. Call before jax is imported: launch.py and each
  grid lane (for its own cores) do. An XLA_FLAGS that already sets the count is kept unless `override`.

  Why: on a CPU, XLA runs one device's step on all its cores less well than one step per core with the batch split
  (benchmarks/savi_speed.py and bc_speed.py time both; the `:small` figures: results/small/README.md).
  """
  flags_now = os.environ.get("XLA_FLAGS", "").split()
  given = [f for f in flags_now if f.startswith(HOST_DEVICES_FLAG + "=")]
  if given and not override:
    return int(given[-1].split("=", 1)[1])
  count = len(os.sched_getaffinity(0))
  os.environ["XLA_FLAGS"] = " ".join([f for f in flags_now if f not in given] + [f"{HOST_DEVICES_FLAG}={count}"])
  return count


def exit_process(code: int) -> None:
  """Ends the process with `code` (what `run_app` returned).

  After an interrupt (130, 143) it does not wait for background threads: a checkpoint write the signal broke off
  leaves orbax threads waiting forever for a step that never comes. What they leave is unfinished and ignored (the
  next run resumes from the last complete checkpoint); every finished write was waited for before.
  """
  if code in INTERRUPT_CODES:
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # pylint: disable=protected-access
  sys.exit(code)


def run_app(main: Callable[[Sequence[str]], None], argv: Sequence[str]) -> int:
  """Runs an absl main with UserError (and bad flags) turned into a one-line message and exit status 2."""
  try:
    _check_overrides(argv)
  except UserError as e:
    return errors.print_error(str(e))
  if flags.FLAGS["config"].present == 0 and "config" in flags.FLAGS and flags.FLAGS["config"].value is None:
    return errors.print_error("--config is required, e.g. --config=configs/pick_savi.py:tiny")
  previous = install_signal_handlers()
  try:
    app.run(main, argv=[argv[0]] + [a for a in argv[1:] if not a.startswith("-")], flags_parser=lambda a: a)
  except UserError as e:
    return errors.print_error(str(e))
  except KeyboardInterrupt as e:
    _quiet_after_interrupt()
    print(f"roboshape: {INTERRUPTED}", file=sys.stderr, flush=True)
    return interrupt_code(e)
  except SystemExit as e:
    return 0 if e.code is None else (e.code if isinstance(e.code, int) else 1)
  finally:
    for signum, handler in previous.items():
      signal.signal(signum, handler)
  return 0
