"""`state`: the privileged simulator state as one token per step, the upper bound of any representation.

The token is the state vector of roboshape/envs/state.py with lengths in decimetres (positions, sizes, the finger
opening; x10), so that every field is of order one; quaternions, joint angles and presence flags as they are;
followed by RELATIVE (9 entries): the cube relative to the tool centre point, the goal relative to the tool centre
point and the goal relative to the cube, in units of the controller's position step (0.1 m, so 1 cm reads 0.1).
These are fixed linear maps of the state, so the token holds the same information; they spare the policy learning
small differences of large coordinates, which is where a policy on the raw vector was imprecise
(results/small/pick_state/README.md). It needs a dataset that stores `observation/state` (every dataset collected
since the field exists).
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
  text = state_lib.describe() + str(token_scale().tolist()) + str(RELATIVE) + str(POSITION_STEP)
  return hashlib.sha1(text.encode()).hexdigest()[:12]


RELATIVE = (("cube_pos", "tcp_pos"), ("goal_pos", "tcp_pos"), ("goal_pos", "cube_pos"))   # (a, b): (a - b) / 0.1
POSITION_STEP = 0.1     # metres per unit of the controller's position action
TOKEN_DIM = state_lib.DIM + 3 * len(RELATIVE)


def _step(params, carry, obs):
  """obs {"state": float [B, DIM]} -> (tokens float32 [B, 1, TOKEN_DIM], carry)."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  state = jnp.asarray(obs["state"], jnp.float32)
  cuts = state_lib.slices()
  relative = [(state[:, cuts[a]] - state[:, cuts[b]]) / POSITION_STEP for a, b in RELATIVE]
  return jnp.concatenate([state * params["scale"]] + relative, axis=-1)[:, None, :], carry


def _build(config, workdir: str):
  del config, workdir
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  return FrozenEncoder(name="state", params={"scale": token_scale()}, step=_step,
                       init_state=lambda batch_size: (), num_tokens=1, token_dim=TOKEN_DIM,
                       identity=f"state:{_layout_hash()}", inputs=("state",))


encoders.register(encoders.Kind(
    name="state", inputs=("state",), pretrain="", build=_build, title="State",
    description="the privileged simulator state as one token (control: the upper bound)"))
