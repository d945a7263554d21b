"""`state`: the privileged simulator state as one token per step, the upper bound of any representation.

The token is the state vector of roboshape/envs/state.py with lengths in decimetres (positions, sizes, the finger
opening; x10), so that every field is of order one; quaternions, joint angles and presence flags as they are;
followed by RELATIVE (9 entries): the cube relative to the tool centre point, the goal relative to the tool centre
point and the goal relative to the cube, in units of the controller's position step (0.1 m, so 1 cm reads 0.1).
These are fixed linear maps of the state, so the token holds the same information; they spare the policy learning
small differences of large coordinates, which is where a policy on the raw vector was imprecise
(`git show cb0d979:results/small/pick_state/README.md`). It needs a dataset that stores `observation/state` (every
dataset collected since the field exists).

`state.withhold` names FIELDS of the state vector that the token leaves out (their entries zero, and every RELATIVE
entry computed from one of them zero): an ablation that says what a field is worth to the policy, e.g. the cube's
orientation, of which the `objects` token holds nothing (its fields: roboshape/encoders/objects.py).
`state.relative` False zeroes every RELATIVE entry: the state with absolute positions only, the rung of the pick
ladder between the state token and object tokens (results/small/recipe) that says what the relative entries are worth.
"""
import numpy as np

from roboshape.encoders import registry
from roboshape.envs import state as state_lib
from roboshape.errors import UserError


def token_scale(withhold=()) -> np.ndarray:
  """float32 [DIM]: the factor each entry of the state vector is multiplied by in the token (0 for the fields in
  `withhold`)."""
  scale = np.ones((state_lib.DIM,), np.float32)
  cuts = state_lib.slices()
  for name in ("tcp_pos", "gripper", "cube_pos", "goal_pos"):
    scale[cuts[name]] = 10.0
  rows = scale[cuts["distractors"]].reshape(state_lib.MAX_DISTRACTORS, 5)
  rows[:, :4] = 10.0
  scale[cuts["distractors"]] = rows.reshape(-1)
  for name in withhold:
    scale[cuts[name]] = 0.0
  return scale


def relative_scale(withhold=()) -> np.ndarray:
  """float32 [len(RELATIVE)]: 1 for each RELATIVE entry, 0 where it is computed from a withheld field."""
  return np.array([0.0 if (a in withhold or b in withhold) else 1.0 for a, b in RELATIVE], np.float32)


def _layout_hash(withhold=(), relative: bool = True) -> str:
  import hashlib  # pylint: disable=import-outside-toplevel
  text = state_lib.describe() + str(token_scale().tolist()) + str(RELATIVE) + str(POSITION_STEP)
  if withhold:     # the full token's hash is the one every cache made before the option existed carries
    text += f" withhold {sorted(withhold)}"
  if not relative:
    text += " absolute only"
  return hashlib.sha1(text.encode()).hexdigest()[:12]


RELATIVE = (("cube_pos", "tcp_pos"), ("goal_pos", "tcp_pos"), ("goal_pos", "cube_pos"))   # (a, b): (a - b) / 0.1
POSITION_STEP = 0.1     # metres per unit of the controller's position action
TOKEN_DIM = state_lib.DIM + 3 * len(RELATIVE)


def _step(params, carry, obs):
  """obs {"state": float [B, DIM]} -> (tokens float32 [B, 1, TOKEN_DIM], carry)."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  state = jnp.asarray(obs["state"], jnp.float32)
  cuts = state_lib.slices()
  relative = [(state[:, cuts[a]] - state[:, cuts[b]]) * (params["relative"][i] / POSITION_STEP)
              for i, (a, b) in enumerate(RELATIVE)]
  return jnp.concatenate([state * params["scale"]] + relative, axis=-1)[:, None, :], carry


def withheld(config) -> tuple:
  """The fields config.state.withhold names (() without a config)."""
  return () if config is None else tuple(config.state.withhold)


def relative_on(config) -> bool:
  """config.state.relative (True without a config)."""
  return True if config is None else bool(config.state.relative)


def check(config) -> None:
  """Raises UserError unless state.withhold is a tuple of distinct FIELDS names."""
  names = tuple(name for name, _, _ in state_lib.FIELDS)
  value = config.state.withhold
  if isinstance(value, str) or not isinstance(value, (tuple, list)) or any(v not in names for v in value) or len(
      set(value)) != len(value):
    raise UserError(f"state.withhold={value!r}: use a tuple of distinct state fields among {', '.join(names)} "
                    "(() withholds nothing).")


def _build(config, workdir: str):
  del workdir
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  withhold, relative = withheld(config), relative_on(config)
  return FrozenEncoder(name="state", params={"scale": token_scale(withhold),
                                             "relative": relative_scale(withhold) * float(relative)},
                       step=_step, init_state=lambda batch_size: (), num_tokens=1, token_dim=TOKEN_DIM,
                       identity=f"state:{_layout_hash(withhold, relative)}", inputs=("state",))


registry.register(registry.Kind(
    name="state", inputs=("state",), pretrain="", build=_build, title="State",
    description="the privileged simulator state as one token (control: the upper bound)",
    sections=("state",), check=check, family="privileged", order=6, tokens=lambda config: f"1 x {TOKEN_DIM}"))
