"""Orbax checkpoints for every training stage: periodic saves, keep the last N, resume at the saved step.

  ckpt = Checkpointer(rundir.checkpoints(rundir.pretrain_dir(workdir, "savi")), keep=3)
  state, step = ckpt.resume(state)       # the latest step that restores (or `state` itself and step 0)
  ckpt.save(step, state)                 # asynchronous; `ckpt.close()` waits for it
  params, step = ckpt.restore_params_latest(like)   # serving: the parameters alone, no optimizer state

A step holds two orbax items: "state", the whole train state (step, params, optimizer moments), which training
resumes from, and "params", the train state's "params" saved again on their own, which serving restores without
building an optimizer. A checkpoint written before the "params" item existed (one item, orbax's "default") still
restores: its params are read out of the whole state, restored as saved.

Checkpoints travel between device counts: a step saved by a run over several devices (launch.py makes each CPU core
one, a GPU machine has its GPUs) restores in a process with any other devices. Orbax records each array's sharding
(the saving process's mesh) and, given no sharding to restore onto, tries to rebuild it, which fails on other
devices ("Topology mismatch"). So every restore here names the sharding: that of the target's leaves where they have
one (a train state the caller already placed on its mesh), else this process's first device; the caller places
the result where it wants it (the train loops put the state on their own mesh).

A damaged checkpoint (a truncated or corrupted file) does not stop a run: `restore_latest` and `resume` warn in one
line and fall back to the next older step that restores; `resume` also moves the damaged steps aside (to
damaged_step_<N>, which orbax ignores) so that training can write those steps again. A step is damaged only when it
does not restore even as saved (the shapes and dtypes its own metadata records, onto this process's devices). A step
that restores as saved but not into the caller's structure (another config's model, shapes or optimizer) is intact:
that is a one-line UserError naming the safe action (the config that wrote it), with no fallback to an older step
and nothing moved. When no step restores and every one is damaged, the error is one line that says what to do.

A full disk while saving is an OSError(ENOSPC) naming the checkpoint folder, raised by `save`, `wait` or `close`
(orbax writes in the background and raises an earlier save's error at the next call). The step being written stays
a temporary folder that orbax never lists (and removes when that step is saved again), so the last complete step
is what restores. What orbax's threads log about the failure themselves is dropped (`_quiet_background_reports`):
the caller's error says it once (roboshape/stages.py makes it one line).
"""
import contextlib
import errno
import gc
import io
import logging
import os
import sys
import time
import warnings
from typing import Any, Iterator, List, NamedTuple, Optional, Tuple

import jax
import orbax.checkpoint as ocp

from roboshape import fileio
from roboshape.errors import UserError

DAMAGED_PREFIX = "damaged_step_"
STATE, PARAMS, LEGACY = "state", "params", "default"     # the items of a step (LEGACY: before "params" existed)


class Checkpointer:
  """A thin wrapper over `ocp.CheckpointManager` with the StandardSave/StandardRestore handlers (named up front, so
  a step's metadata, what restoring it as saved needs, can be read before anything was restored)."""

  def __init__(self, directory: str, keep: int = 3):
    self.directory = os.path.abspath(directory)
    _quiet_background_reports()
    self._manager = ocp.CheckpointManager(
        self.directory, item_handlers={name: ocp.StandardCheckpointHandler() for name in (STATE, PARAMS, LEGACY)},
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
    with self._disk_full_named():
      self._manager.save(step, args=ocp.args.Composite(**items), force=True)

  def restore_params(self, like: Any, step: Optional[int] = None) -> Any:
    """The params of the checkpoint at `step` restored into the structure, shapes and dtypes of `like`, on `like`'s
    shardings where its leaves have one (else on this process's first device), whatever devices saved it.

    step None: the newest step whose params restore (`restore_params_latest`). A given step that does not restore is
    a one-line UserError.
    """
    if step is None:
      return self.restore_params_latest(like)[0]
    return self._given_step(step, like, PARAMS)

  def restore_params_latest(self, like: Any) -> Tuple[Any, int]:
    """(params, step) of the newest checkpoint whose params restore into `like`'s structure; as `restore_latest`
    (without setting anything aside)."""
    return self._newest(like, False, PARAMS)

  def restore_latest(self, like: Any, set_aside: bool = False) -> Tuple[Any, int]:
    """(state, step) of the newest checkpoint that restores into `like`'s structure.

    A newer step that is damaged (`_try_restore`) is reported in one warning line and skipped; with `set_aside`
    it is also moved to <directory>/damaged_step_<N> once an older step has restored. Raises FileNotFoundError
    when there is no checkpoint, and UserError when a step is intact but does not restore into `like` (nothing
    is skipped or moved then: an older step would not fit either) or when every step is damaged (nothing moved).
    """
    return self._newest(like, set_aside, STATE)

  def _given_step(self, step: int, like: Any, item: str) -> Any:
    value, failure = self._try_restore(step, like, item)
    if failure is None:
      return value
    if not failure.damaged:
      raise UserError(self._intact_message(step, failure.reason))
    raise UserError(f"checkpoint step {step} in {self.directory} does not restore ({failure.reason}); "
                    f"load another step (saved: {self.all_steps()}).")

  def _newest(self, like: Any, set_aside: bool, item: str) -> Tuple[Any, int]:
    steps = self.all_steps()[::-1]
    if not steps:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    failed = []
    for i, step in enumerate(steps):
      state, failure = self._try_restore(step, like, item)
      if failure and not failure.damaged:
        raise UserError(self._intact_message(step, failure.reason))
      if failure:
        failed.append((step, failure.reason))
        if i + 1 < len(steps):
          _warn(f"[roboshape] checkpoint step {step} in {self.directory} does not restore ({failure.reason}); "
                f"falling back to step {steps[i + 1]}")
        continue
      if set_aside and failed:
        self._set_aside([s for s, _ in failed])
      return state, step
    step, reason = failed[0]
    raise UserError(f"no checkpoint in {self.directory} restores (step {step}: {reason}), and none reads even as "
                    f"saved, so every one is damaged: copy {self.directory} back from a backup if you have one; "
                    f"otherwise move it away (nothing here was moved) to start this training over.")

  def _intact_message(self, step: int, reason: str) -> str:
    """The one-line error for a step that restores as saved but not into the caller's structure: the safe action
    (the config that wrote it) first; nothing suggests moving an intact checkpoint away."""
    return (f"run with the config these checkpoints were trained with (the workdir's config.json, without "
            f"--config overrides that change the model or its optimizer): checkpoint step {step} in "
            f"{self.directory} is intact but does not restore into this config's structure ({reason}); "
            "nothing was moved or changed.")

  def resume(self, state: Any) -> Tuple[Any, int]:
    """(state, step) to go on training from: the newest checkpoint that restores into `state`'s structure, with
    damaged newer steps set aside (see `restore_latest`); `state` itself and step 0 when there is no checkpoint."""
    if self.latest_step() is None:
      return state, 0
    return self.restore_latest(state, set_aside=True)

  def restores(self, step: int) -> bool:
    """Whether checkpoint `step` restores as saved (its own shapes and dtypes, onto this process's devices): whether
    it is undamaged."""
    return self._try_restore(step, None)[1] is None

  def wait(self) -> None:
    with self._disk_full_named():
      self._manager.wait_until_finished()

  def close(self) -> None:
    try:
      self.wait()
    finally:
      self._manager.close()     # a save's error is raised once: closing after it waits for nothing more

  @contextlib.contextmanager
  def _disk_full_named(self) -> Iterator[None]:
    """Raises a full disk that orbax met while saving (here, or in its threads for an earlier save) as
    OSError(ENOSPC) naming this checkpoint folder; other errors as they are."""
    try:
      yield
    except Exception as e:  # pylint: disable=broad-except
      if not fileio.disk_full(e):
        raise
      raise OSError(errno.ENOSPC, f"{fileio.NO_SPACE} while saving a checkpoint", self.directory) from e

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

  def _try_restore(self, step: int, like: Any, item: str = STATE) -> Tuple[Any, Optional["_Failure"]]:
    """(the `item` of checkpoint `step`, None) when it restores into `like`'s structure, else (None, why).

    `like`: the target (arrays or ShapeDtypeStructs), restored onto its leaves' shardings where they have one, else
    onto this process's first device; None restores the step as saved (`_read`). A legacy checkpoint (one
    "default" item, the whole state) gives its params restored as saved, checked against `like`'s shapes.
    A failure is damage only when the item does not restore as saved either; a step that does is intact and its
    failure a mismatch with `like` (another config's structure or shapes), which `_Failure.damaged` tells apart.
    """
    legacy = os.path.isdir(os.path.join(self.directory, str(step), LEGACY))
    stored = LEGACY if legacy else item
    as_saved = like is None or (legacy and item == PARAMS)
    with _quiet() as sink:
      # A step whose metadata already shows other shapes (another config's model) is not read into `like`: that
      # read would fail and leave reads behind to settle, which costs a second or more. Reading it as saved says
      # whether it is intact, as below, and an intact read abandons nothing.
      shapes = None if as_saved else self._other_shapes(step, stored, like)
      if shapes:
        damaged = not self._reads_as_saved(step, stored)
        if damaged:
          _settle(sink)
        return None, _Failure(shapes, damaged)
      try:
        value = self._read(step, stored, None if as_saved else jax.tree.map(_target, like))
        if not (legacy and item == PARAMS):
          return value, None
        mismatch = _mismatch(value[PARAMS], like)
        return (None, _Failure(mismatch, False)) if mismatch else (value[PARAMS], None)
      except Exception as e:  # pylint: disable=broad-except
        reason = _reason(e)
      _settle(sink)
      damaged = as_saved or not self._reads_as_saved(step, stored)
      if damaged and not as_saved:
        _settle(sink)
    return None, _Failure(reason, damaged)

  def _other_shapes(self, step: int, stored: str, like: Any) -> Optional[str]:
    """Why `like` cannot hold the item `stored` of `step`, when its metadata names the same arrays as `like` (by
    their paths in the tree, as orbax stores them) and one of them with another shape; None when the shapes agree
    or the metadata cannot tell (it does not read, or names other arrays: the restore itself then decides)."""
    try:
      metadata = self._manager.item_metadata(step)[stored]
      saved = ocp.tree.to_flat_dict(getattr(metadata, "tree", metadata))
      wanted = ocp.tree.to_flat_dict(ocp.tree.serialize_tree(like, keep_empty_nodes=True))
    except Exception:  # pylint: disable=broad-except
      return None
    if set(saved) != set(wanted):
      return None
    for path in sorted(saved):
      a, b = getattr(saved[path], "shape", None), getattr(wanted[path], "shape", None)
      if a is not None and b is not None and tuple(a) != tuple(b):
        return f"ValueError: saved {'/'.join(map(str, path))} of shape {tuple(a)}, expected {tuple(b)}"
    return None

  def _reads_as_saved(self, step: int, stored: str) -> bool:
    try:
      self._read(step, stored, None)
      return True
    except Exception:  # pylint: disable=broad-except
      return False

  def _read(self, step: int, stored: str, abstract: Any) -> Any:
    """The item `stored` of checkpoint `step` restored into `abstract` (ShapeDtypeStructs with shardings); None:
    as saved, the shapes and dtypes of the step's own metadata on this process's first device (not the saving
    process's devices, which this one may not have)."""
    if abstract is None:
      metadata = self._manager.item_metadata(step)[stored]
      if metadata is None:
        raise FileNotFoundError(f"checkpoint step {step} has no readable {stored!r} item")
      abstract = jax.tree.map(_as_saved, getattr(metadata, "tree", metadata))
    return self._manager.restore(step, args=ocp.args.Composite(
        **{stored: ocp.args.StandardRestore(abstract)}))[stored]

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
  is skipped with a one-line warning); UserError(`missing`) when there is no checkpoint. Builds no optimizer, and
  creates nothing where there is no checkpoint folder (a loader only reads)."""
  if not os.path.isdir(directory):
    raise UserError(missing)
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
  TensorStore spec when collected). Inside `_quiet` they go to `sink`. Each round collects garbage once (which
  frees the abandoned coroutines, so they print now) and then waits until `sink` is unchanged for `quiet_polls`
  polls; it is settled when a whole round added nothing. A collection scans every object of the process (a
  noticeable fraction of a second beside TensorFlow and JAX), so it runs once a round, not once a poll. The
  abandoned reads' coroutines that the collections free also warn that they were never awaited (a RuntimeWarning,
  which a test run records): that warning is ignored here.
  """
  deadline, before = time.monotonic() + limit, -1
  while time.monotonic() < deadline:
    with warnings.catch_warnings():
      warnings.filterwarnings("ignore", message=r"coroutine .* was never awaited", category=RuntimeWarning)
      gc.collect()
    calm, size = 0, sink.tell()
    while calm < quiet_polls and time.monotonic() < deadline:
      time.sleep(poll)
      now = sink.tell()
      calm, size = (calm + 1, size) if now == size else (0, now)
    if size == before:
      return
    before = size


def _abandoned_io(e: Optional[BaseException]) -> bool:
  """Whether `e` (or what caused it) is the failure of a read or write that orbax abandoned when another one of
  the same restore or save failed."""
  while e is not None:
    text = str(e)
    if ("reading array index" in text or "OCDBT database" in text or
        (isinstance(e, RuntimeError) and text == "Event loop is closed")):
      return True
    e = e.__cause__ or e.__context__
  return False


def _background_report(error: Optional[BaseException], message: str = "") -> bool:
  """Whether a report from a background thread (an error, a log message) is about an abandoned read or write or a
  full disk: what the caller hears about anyway, from the restore that failed or at the next save or wait."""
  if error is not None and (_abandoned_io(error) or fileio.disk_full(error)):
    return True
  return fileio.NO_SPACE in message


class _BackgroundReportFilter(logging.Filter):
  """Drops the log records of `_background_report`s: asyncio's "exception was never retrieved", and orbax's own
  tracebacks of a failed save (one per thread it ran in)."""

  def filter(self, record: logging.LogRecord) -> bool:
    return not _background_report(record.exc_info[1] if record.exc_info else None, record.getMessage())


def _quiet_background_reports() -> None:
  """Drops the `_background_report`s of orbax's and asyncio's threads: what reads abandoned by a failed restore
  report when they end after `_settle` (or, through a logging handler that holds the real stderr, during it), and
  what a save that met a full disk logs from each thread; installed once per process, by the first Checkpointer."""
  if getattr(_quiet_background_reports, "installed", False):
    return
  _quiet_background_reports.installed = True
  previous = sys.unraisablehook

  def hook(unraisable):
    if not _background_report(unraisable.exc_value):
      previous(unraisable)

  sys.unraisablehook = hook
  for name in ("asyncio", "absl"):     # orbax logs through absl
    logging.getLogger(name).addFilter(_BackgroundReportFilter())


class _Failure(NamedTuple):
  """Why a checkpoint step did not restore, and whether it is damaged (does not restore even as saved)."""
  reason: str
  damaged: bool


def _one_device() -> jax.sharding.Sharding:
  return jax.sharding.SingleDeviceSharding(jax.devices()[0])


def _target(leaf: Any) -> Any:
  """A leaf of a restore target: its shape and dtype, on its own sharding (an array placed by this process, a
  ShapeDtypeStruct that names one) or else on this process's first device, never on the saved one."""
  target = ocp.utils.to_shape_dtype_struct(leaf)
  if isinstance(target, jax.ShapeDtypeStruct) and target.sharding is None:
    return jax.ShapeDtypeStruct(target.shape, target.dtype, sharding=_one_device())
  return target


def _as_saved(leaf: Any) -> Any:
  """A leaf of a step's metadata as a restore target on this process's first device (arrays; other leaves as
  they are)."""
  if hasattr(leaf, "shape") and hasattr(leaf, "dtype"):
    return jax.ShapeDtypeStruct(tuple(leaf.shape), leaf.dtype, sharding=_one_device())
  return leaf


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
