"""`state`: the privileged simulator state as one token per step, the upper bound of any representation.

The token is the state vector of roboshape/envs/state.py with lengths in decimetres (positions, sizes, the finger
opening; x10), so that every field is of order one; quaternions, joint angles and presence flags as they are. It
needs a dataset that stores `observation/state` (every dataset collected since the field exists).
"""
import numpy as np

from roboshape import encoders
from roboshape.envs import state as state_lib


def token_scale() -> np.ndarray:
  """float32 [DIM]: the factor each entry of the state vector is multiplied by in the token."""
  scale = np.ones((state_lib.DIM,), np.float32)
  cuts = state_lib.slices()
  for name in ("tcp_pos", "gripper", "cube_pos", "goal_pos"):
    scale[cuts[name]] = 10.0
  rows = scale[cuts["distractors"]].reshape(state_lib.MAX_DISTRACTORS, 5)
  rows[:, :4] = 10.0
  scale[cuts["distractors"]] = rows.reshape(-1)
  return scale


def _layout_hash() -> str:
  import hashlib  # pylint: disable=import-outside-toplevel
  return hashlib.sha1((state_lib.describe() + str(token_scale().tolist())).encode()).hexdigest()[:12]


def _step(params, carry, obs):
  """obs {"state": float [B, DIM]} -> (tokens float32 [B, 1, DIM], carry)."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  return (jnp.asarray(obs["state"], jnp.float32) * params["scale"])[:, None, :], carry


def _build(config, workdir: str):
  del config, workdir
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  return FrozenEncoder(name="state", params={"scale": token_scale()}, step=_step,
                       init_state=lambda batch_size: (), num_tokens=1, token_dim=state_lib.DIM,
                       identity=f"state:{_layout_hash()}", inputs=("state",))


encoders.register(encoders.Kind(
    name="state", inputs=("state",), pretrain="", build=_build, title="State",
    description="the privileged simulator state as one token (control: the upper bound)"))
