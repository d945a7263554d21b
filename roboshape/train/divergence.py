"""Stopping a training stage at its first non-finite loss or gradient norm, the same for every training stage.

  divergence.check({"loss": loss, "gradient norm": norm}, step, ckpt, stage="train_policy", what="the policy's",
                   fields={"policy.train.learning_rate": 1e6})
  if divergence.finite(state["params"]): ckpt.save(step, state)

Why: a loss that turns NaN or inf never comes back, and a run that goes on writes checkpoints of NaN parameters,
logs NaN scalars and marks its stage done, so the failure surfaces stages later (an evaluation that cannot step
the simulator) without its cause. `check` raises `Diverged`, a UserError (one line, exit status 2): the stage, the
step, the value, the checkpoint that stays (the last one written: every one was finite, as the training loops check
each step's metrics before anything is logged or saved, and `finite` the parameters before every save), and the
config fields to change. The stage is not marked done (roboshape/rundir.py's stage log records an attempt that
raised as unfinished), so nothing downstream takes its output for finished.
"""
import functools
from typing import Any, Mapping

import numpy as np

from roboshape.errors import UserError


class Diverged(UserError):
  """A training stage met a non-finite loss or gradient norm; the message names the stage, the step and the fields
  to change."""


def non_finite(values: Mapping[str, Any]) -> dict:
  """{name: value} of the entries of `values` (scalars) that are NaN or inf."""
  return {name: float(value) for name, value in values.items() if not np.isfinite(float(value))}


def check(values: Mapping[str, Any], step: int, ckpt, *, stage: str, what: str, fields: Mapping[str, Any],
          detail: str = "") -> None:
  """Raises `Diverged` when a value of `values` ({"loss": ..., "gradient norm": ...}, the metrics of training step
  `step`, counted from 1 as the logs count them) is not finite.

  `ckpt`: the stage's Checkpointer (its newest step is the finite one kept; saves in flight are waited for).
  `what`: whose values, e.g. "the SAVi"; `fields`: {dotted config field: its value}, the settings to lower;
  `detail`: more about the step, e.g. the batch's episode seeds.
  """
  bad = non_finite(values)
  if bad:
    _stop(f"{what} " + " and ".join(f"{name} is {value}" for name, value in bad.items()), step, ckpt, stage,
          fields, detail)


def check_params(params, step: int, ckpt, *, stage: str, what: str, fields: Mapping[str, Any]) -> None:
  """Raises `Diverged` when `params`, about to be saved as checkpoint `step`, are not all finite (`finite`)."""
  if not finite(params):
    _stop(f"{what} parameters are not finite (NaN or inf)", step, ckpt, stage, fields, "")


def _stop(found: str, step: int, ckpt, stage: str, fields: Mapping[str, Any], detail: str) -> None:
  ckpt.wait()
  latest = ckpt.latest_step()
  kept = (f"the last checkpoint, step {latest}, is finite and kept in {ckpt.directory}" if latest is not None
          else f"no checkpoint was written yet ({ckpt.directory})")
  lower = " or ".join(f"--config.{field} (now {value!r})" for field, value in fields.items())
  raise Diverged(f"{stage}: {found} at step {step}{detail}; training stopped there: {kept}, and the stage is not "
                 f"done. Lower {lower} and run again with --redo={stage} (which sets this attempt aside), or in "
                 "another --workdir.")


def finite(tree) -> bool:
  """Whether every leaf of a pytree of arrays (a train state's params) is finite: what a checkpoint must be. One
  compiled call for the whole tree (op by op, each leaf's shape would compile two small programs of its own)."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.inexact)]
  return bool(_all_finite()(leaves)) if leaves else True


@functools.lru_cache(maxsize=None)
def _all_finite():
  """The jitted check of `finite`: a list of arrays -> whether all their entries are finite."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  return jax.jit(lambda leaves: jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])))
