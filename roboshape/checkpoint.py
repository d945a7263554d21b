"""Orbax checkpoints for every training stage: periodic saves, keep the last N, resume at the saved step.

  ckpt = Checkpointer(rundir.checkpoints(rundir.savi_dir(workdir)), keep=3)
  state, step = ckpt.resume(state)       # the latest step that restores (or `state` itself and step 0)
  ckpt.save(step, state)                 # asynchronous; `ckpt.close()` waits for it
  params, step = ckpt.restore_params_latest(like)   # serving: the parameters alone, no optimizer state

A step holds two orbax items: "state", the whole train state (step, params, optimizer moments), which training
resumes from, and "params", the train state's "params" saved again on their own, which serving restores without
building an optimizer. A checkpoint written before the "params" item existed (one item, orbax's "default") still
restores: its params are read out of the whole state, restored as saved.

A damaged checkpoint (a truncated or corrupted file) does not stop a run: `restore_latest` and `resume` warn in one
line and fall back to the next older step that restores; `resume` also moves the damaged steps aside (to
damaged_step_<N>, which orbax ignores) so that training can write those steps again. When no step restores, the
error is one line that says what to do.
"""
import contextlib
import gc
import io
import logging
import os
import sys
import time
from typing import Any, Iterator, List, Optional, Tuple

import jax
import orbax.checkpoint as ocp

from roboshape.errors import UserError

DAMAGED_PREFIX = "damaged_step_"
STATE, PARAMS, LEGACY = "state", "params", "default"     # the items of a step (LEGACY: before "params" existed)


class Checkpointer:
  """A thin wrapper over `ocp.CheckpointManager` with the StandardSave/StandardRestore handlers."""

  def __init__(self, directory: str, keep: int = 3):
    self.directory = os.path.abspath(directory)
    self._manager = ocp.CheckpointManager(
        self.directory, item_names=(STATE, PARAMS, LEGACY),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True))

  def latest_step(self) -> Optional[int]:
    return self._manager.latest_step()

  def all_steps(self) -> List[int]:
    """Every saved step, oldest first."""
    return sorted(self._manager.all_steps())

  def save(self, step: int, state: Any) -> None:
    """Saves `state` as the "state" item of `step`, and its "params" (when it has them) as the "params" item."""
    items = {STATE: ocp.args.StandardSave(state)}
    if isinstance(state, dict) and PARAMS in state:
      items[PARAMS] = ocp.args.StandardSave(state[PARAMS])
    self._manager.save(step, args=ocp.args.Composite(**items), force=True)

  def restore(self, like: Any, step: Optional[int] = None) -> Any:
    """Restores the checkpoint at `step` into the structure, shapes and dtypes of `like`.

    step None: the latest step that restores (see `restore_latest`). A given step that does not restore is a
    one-line UserError.
    """
    if step is None:
      return self.restore_latest(like)[0]
    state, failure = self._try_restore(step, like)
    if failure:
      raise UserError(f"checkpoint step {step} in {self.directory} does not restore ({failure}); "
                      f"load another step (saved: {self.all_steps()}).")
    return state

  def restore_params(self, like: Any, step: Optional[int] = None) -> Any:
    """The params of the checkpoint at `step` (None: the latest that restores), as `restore` for the state."""
    if step is None:
      return self.restore_params_latest(like)[0]
    params, failure = self._try_restore(step, like, PARAMS)
    if failure:
      raise UserError(f"checkpoint step {step} in {self.directory} does not restore ({failure}); "
                      f"load another step (saved: {self.all_steps()}).")
    return params

  def restore_params_latest(self, like: Any) -> Tuple[Any, int]:
    """(params, step) of the newest checkpoint whose params restore into `like`'s structure; as `restore_latest`
    (without setting anything aside)."""
    return self._newest(like, False, PARAMS)

  def restore_latest(self, like: Any, set_aside: bool = False) -> Tuple[Any, int]:
    """(state, step) of the newest checkpoint that restores into `like`'s structure.

    A newer step that fails to restore is reported in one warning line and skipped; with `set_aside` it is also
    moved to <directory>/damaged_step_<N> once an older step has restored. Raises FileNotFoundError when there is
    no checkpoint and UserError when none restores (nothing is moved then).
    """
    return self._newest(like, set_aside, STATE)

  def _newest(self, like: Any, set_aside: bool, item: str) -> Tuple[Any, int]:
    steps = self.all_steps()[::-1]
    if not steps:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    failed = []
    for i, step in enumerate(steps):
      state, failure = self._try_restore(step, like, item)
      if failure:
        failed.append((step, failure))
        if i + 1 < len(steps):
          _warn(f"[roboshape] checkpoint step {step} in {self.directory} does not restore ({failure}); "
                f"falling back to step {steps[i + 1]}")
        continue
      if set_aside and failed:
        self._set_aside([s for s, _ in failed])
      return state, step
    step, reason = failed[0]
    raise UserError(f"no checkpoint in {self.directory} restores (step {step}: {reason}): if the config changed "
                    f"since they were written, run with the workdir's config.json; otherwise move {self.directory} "
                    "away to start this training over.")

  def resume(self, state: Any) -> Tuple[Any, int]:
    """(state, step) to go on training from: the newest checkpoint that restores into `state`'s structure, with
    damaged newer steps set aside (see `restore_latest`); `state` itself and step 0 when there is no checkpoint."""
    if self.latest_step() is None:
      return state, 0
    return self.restore_latest(state, set_aside=True)

  def restore_or(self, state: Any) -> Any:
    """The latest checkpoint restored into `state`'s structure, or `state` unchanged when there is none."""
    return self.resume(state)[0]

  def restores(self, step: int) -> bool:
    """Whether checkpoint `step` restores (as saved, without a target structure)."""
    return self._try_restore(step, None)[1] is None

  def wait(self) -> None:
    self._manager.wait_until_finished()

  def close(self) -> None:
    self._manager.wait_until_finished()
    self._manager.close()

  def __enter__(self):
    return self

  def __exit__(self, exc_type, exc, tb):
    if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
      self._close_after_interrupt()
      return
    self.close()

  def _close_after_interrupt(self) -> None:
    """Finishes the checkpoint in flight, quietly: one the interrupt broke off (orbax then logs errors about it)
    is left unfinished, and the next run resumes from the last complete one."""
    level = logging.root.manager.disable
    logging.disable(logging.CRITICAL)
    try:
      self.close()
    except Exception:  # pylint: disable=broad-except
      pass
    finally:
      logging.disable(level)

  def _try_restore(self, step: int, like: Any, item: str = STATE) -> Tuple[Any, Optional[str]]:
    """(the `item` of checkpoint `step`, None) when it restores into `like`'s structure (None: as saved), else
    (None, why). A legacy checkpoint (one "default" item, the whole state) gives its params restored as saved,
    checked against `like`'s shapes."""
    abstract = None if like is None else jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
    legacy = os.path.isdir(os.path.join(self.directory, str(step), LEGACY))
    _drop_stragglers()
    with _quiet() as sink:
      try:
        if not legacy:
          return self._manager.restore(step, args=ocp.args.Composite(
              **{item: ocp.args.StandardRestore(abstract)}))[item], None
        if item == STATE:
          return self._manager.restore(step, args=ocp.args.Composite(
              **{LEGACY: ocp.args.StandardRestore(abstract)}))[LEGACY], None
        params = self._manager.restore(step, args=ocp.args.Composite(
            **{LEGACY: ocp.args.StandardRestore(None)}))[LEGACY][PARAMS]
        return params, _mismatch(params, abstract)
      except Exception as e:  # pylint: disable=broad-except
        failure = _reason(e)
      _settle(sink)
    return None, failure

  def _set_aside(self, steps: List[int]) -> None:
    """Moves damaged steps to <directory>/damaged_step_<N> (kept for inspection, ignored by orbax)."""
    for step in steps:
      target = os.path.join(self.directory, f"{DAMAGED_PREFIX}{step}")
      suffix = 1
      while os.path.exists(target):
        suffix += 1
        target = os.path.join(self.directory, f"{DAMAGED_PREFIX}{step}_{suffix}")
      os.rename(os.path.join(self.directory, str(step)), target)
      _warn(f"[roboshape] moved the damaged checkpoint step {step} to {target}")
    self._manager.reload()


def restore_params(directory: str, like: Any, missing: str) -> Tuple[Any, int]:
  """(params, step) of the newest checkpoint in `directory` whose params restore into `like` (a damaged newer one
  is skipped with a one-line warning); UserError(`missing`) when there is no checkpoint. Builds no optimizer."""
  ckpt = Checkpointer(directory)
  try:
    if ckpt.latest_step() is None:
      raise UserError(missing)
    return ckpt.restore_params_latest(like)
  finally:
    ckpt.close()


@contextlib.contextmanager
def _quiet() -> Iterator[io.StringIO]:
  """Swallows what goes to sys.stderr and `sys.unraisablehook` meanwhile (see `_settle`)."""
  hook, stderr, sink = sys.unraisablehook, sys.stderr, io.StringIO()
  sys.unraisablehook, sys.stderr = (lambda unraisable: sink.write("unraisable\n")), sink
  try:
    yield sink
  finally:
    sys.unraisablehook, sys.stderr = hook, stderr


def _settle(sink: io.StringIO, poll: float = 0.05, quiet_polls: int = 6, limit: float = 3.0) -> None:
  """Waits (at most `limit` seconds) until the reads a failed restore abandoned have ended.

  Orbax reads every array at once and gives up on the first that fails; the others end later, on other threads,
  each printing a traceback ("Event loop is closed", or "Exception ignored in <coroutine>" with a page of
  TensorStore spec when collected). Inside `_quiet` they go to `sink`: this waits until nothing more comes.
  """
  deadline, calm, seen = time.monotonic() + limit, 0, -1
  while time.monotonic() < deadline and calm < quiet_polls:
    gc.collect()
    time.sleep(poll)
    size = sink.tell()
    calm, seen = (calm + 1, seen) if size == seen else (0, size)


def _abandoned_read(e: Optional[BaseException]) -> bool:
  """Whether `e` (or what caused it) is the failure of a read a failed restore abandoned."""
  while e is not None:
    text = str(e)
    if ("reading array index" in text or "OCDBT database" in text or
        (isinstance(e, RuntimeError) and text == "Event loop is closed")):
      return True
    e = e.__cause__ or e.__context__
  return False


class _AbandonedReadFilter(logging.Filter):
  """Drops asyncio's "exception was never retrieved" about an abandoned read."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not (record.exc_info and _abandoned_read(record.exc_info[1]))


def _drop_stragglers() -> None:
  """Drops what reads abandoned by a failed restore report when they end after `_settle` (or, through a logging
  handler that holds the real stderr, during it); installed once per process."""
  if getattr(_drop_stragglers, "installed", False):
    return
  _drop_stragglers.installed = True
  previous = sys.unraisablehook

  def hook(unraisable):
    if not _abandoned_read(unraisable.exc_value):
      previous(unraisable)

  sys.unraisablehook = hook
  logging.getLogger("asyncio").addFilter(_AbandonedReadFilter())


def _mismatch(tree: Any, like: Any) -> Optional[str]:
  """None when `tree` has the structure and shapes of `like` (or `like` is None), else why not."""
  if like is None:
    return None
  if jax.tree.structure(tree) != jax.tree.structure(like):
    return "ValueError: the saved params have another structure"
  for a, b in zip(jax.tree.leaves(tree), jax.tree.leaves(like)):
    if tuple(a.shape) != tuple(b.shape):
      return f"ValueError: saved params of shape {tuple(a.shape)}, expected {tuple(b.shape)}"
  return None


def _reason(e: BaseException) -> str:
  """The first line of an exception, short: what a one-line warning says about it."""
  lines = [l.strip() for l in str(e).splitlines() if l.strip()]
  text = lines[0] if lines else ""
  text = text.split(" See full TensorStore details")[0]
  return f"{type(e).__name__}: {text[:160]}" if text else type(e).__name__


def _warn(message: str) -> None:
  print(message, file=sys.stderr, flush=True)
