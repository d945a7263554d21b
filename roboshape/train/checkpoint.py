"""Orbax checkpoints for every training stage: periodic saves, keep the last N, resume at the saved step.

  ckpt = Checkpointer(os.path.join(workdir, "savi", "checkpoints"), keep=3)
  state = ckpt.restore_or(state)         # the latest saved state, or `state` itself when there is none
  ckpt.save(step, state)                 # asynchronous; `ckpt.close()` waits for it
"""
import os
from typing import Any, Optional

import jax
import orbax.checkpoint as ocp


class Checkpointer:
  """A thin wrapper over `ocp.CheckpointManager` with the StandardSave/StandardRestore handlers."""

  def __init__(self, directory: str, keep: int = 3):
    self.directory = os.path.abspath(directory)
    self._manager = ocp.CheckpointManager(
        self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True))

  def latest_step(self) -> Optional[int]:
    return self._manager.latest_step()

  def save(self, step: int, state: Any) -> None:
    self._manager.save(step, args=ocp.args.StandardSave(state), force=True)

  def restore(self, like: Any, step: Optional[int] = None) -> Any:
    """Restores the checkpoint at `step` (default: the latest) into the structure, shapes and dtypes of `like`."""
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"no checkpoint in {self.directory}")
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
    return self._manager.restore(step, args=ocp.args.StandardRestore(abstract))

  def restore_or(self, state: Any) -> Any:
    """The latest checkpoint restored into `state`'s structure, or `state` unchanged when there is none."""
    return state if self.latest_step() is None else self.restore(state)

  def wait(self) -> None:
    self._manager.wait_until_finished()

  def close(self) -> None:
    self._manager.wait_until_finished()
    self._manager.close()

  def __enter__(self):
    return self

  def __exit__(self, *exc):
    self.close()
