"""Proprioception: one more token per frame holding the robot's own pose, appended to any encoder's tokens.

`policy.proprio=True` wraps the run's encoder (`with_proprio`): its step reads `state` besides the encoder's own
inputs and appends, after the encoder's N tokens, one token made of the state vector's FIELDS (roboshape/envs/
state.py): the tool centre point's position and orientation and the finger opening, lengths in decimetres as the
`state` encoder scales them. Every token gets one more entry, a flag that is 1 on the proprioception token and 0 on
the encoder's, so the trunk's shared token projection can tell the two apart; the shorter of the two is padded with
zeros to the longer's width. An encoder token that is all zero (the `objects` encoder's absent object) stays all
zero, so the trunk still masks it out.

With `policy.hand_relative` (`with_proprio(..., hand_relative=True)`), every encoder token also carries where its
object is relative to the hand: (its object's world point - the tool centre point) / RELATIVE_STEP (0.1 m, the
controller's position step, as the `state` token's relative entries), three entries after the token's own, zero
where the encoder cannot place the token (FrozenEncoder.points: an absent object, a pixel without depth). The
point comes from the token alone (the `objects` token's centroid and depth through the camera's calibration,
roboshape/envs/camera.py; a `poses` token's position), never from which token it is, so the trunk gets the
geometry a grasp depends on without knowing which token is the hand or the cube; the tool centre point is
proprioception, which the robot has.

The cache, training and closed-loop control all go through the wrapped encoder, so the token a policy is trained
on and the one it acts on come from the same `observation/state` fields (the dataset's at training, the
simulator worker's at control time).
"""
import dataclasses

import numpy as np

from roboshape.envs import state as state_lib
from roboshape.errors import UserError

FIELDS = ("tcp_pos", "tcp_quat", "gripper")
RELATIVE_STEP = 0.1     # metres per unit of the relative entries
_METRES = ("tcp_pos", "gripper")   # lengths, in decimetres in the token (x10)


def indices_and_scale():
  """(int [P] indices into the state vector, float32 [P] factors): the proprioception token's entries."""
  cuts = state_lib.slices()
  idx = np.concatenate([np.arange(cuts[f].start, cuts[f].stop) for f in FIELDS])
  scale = np.concatenate([np.full(cuts[f].stop - cuts[f].start, 10.0 if f in _METRES else 1.0, np.float32)
                          for f in FIELDS])
  return idx, scale


SIZE = len(indices_and_scale()[0])


def token(state) -> np.ndarray:
  """float [..., state_lib.DIM] -> float32 [..., SIZE]: the proprioception entries, lengths in decimetres."""
  idx, scale = indices_and_scale()
  return np.asarray(state, np.float32)[..., idx] * scale


def _wrapped_step(base_step, base_inputs, width, points, params, carry, obs):
  """The base encoder's step with the proprioception token appended: tokens [B, N + 1, width + 1]. The entries'
  indices are fixed (indices_and_scale), their factors live in params["scale"]. With `points` (the base encoder's
  FrozenEncoder.points), each base token first gets its object's position relative to the tool centre point."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape.models import encoder as encoder_lib  # pylint: disable=import-outside-toplevel
  tokens, carry = base_step(params["base"], carry, encoder_lib.select(base_inputs, obs))
  state = jnp.asarray(obs["state"], jnp.float32)
  if points is not None:
    where, valid = points(tokens)                                                         # [B, N, 3], [B, N]
    tcp = state[:, state_lib.slices()["tcp_pos"]]
    relative = jnp.where(valid[..., None], (where - tcp[:, None, :]) / RELATIVE_STEP, 0.0)
    tokens = jnp.concatenate([tokens, relative.astype(tokens.dtype)], axis=-1)
  b, n, d = tokens.shape
  index, _ = indices_and_scale()
  own = state[:, index] * params["scale"]                                                    # [B, P]
  tokens = jnp.concatenate([tokens, jnp.zeros((b, n, width + 1 - d), tokens.dtype)], axis=-1)
  own = jnp.concatenate([own, jnp.zeros((b, width - own.shape[-1]), own.dtype), jnp.ones((b, 1), own.dtype)], -1)
  return jnp.concatenate([tokens, own[:, None, :].astype(tokens.dtype)], axis=1), carry


def with_proprio(encoder, hand_relative: bool = False):
  """The FrozenEncoder `encoder` with one proprioception token per frame, and with `hand_relative` each of its
  tokens' objects relative to the hand (see the module docstring; an encoder without FrozenEncoder.points is a
  UserError then)."""
  import functools  # pylint: disable=import-outside-toplevel
  points = None
  if hand_relative:
    if encoder.points is None:
      raise UserError(f"policy.hand_relative=True: the {encoder.name} encoder's tokens do not say where their "
                      "objects are; use it without policy.hand_relative.")
    points = encoder.points
  width = max(encoder.token_dim + (3 if points else 0), SIZE)
  inputs = tuple(encoder.inputs) + (() if "state" in encoder.inputs else ("state",))
  return dataclasses.replace(
      encoder, params={"base": encoder.params, "scale": indices_and_scale()[1]},
      step=functools.partial(_wrapped_step, encoder.step, tuple(encoder.inputs), width, points),
      num_tokens=encoder.num_tokens + 1, token_dim=width + 1, inputs=inputs, points=None,
      identity=f"{encoder.identity}+proprio:{'+'.join(FIELDS)}" + (f"+relative:{RELATIVE_STEP}" if points else ""))
