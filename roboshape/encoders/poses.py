"""`poses`: one token per object from the simulator's exact poses, an unordered set without ids (a control).

It sits between the `state` token (one vector, every field at a fixed place) and the `objects` tokens (one per
segmentation id, made of what the mask shows): the same kind of unordered set as `objects` (a token does not hold
which object it is, and the trunk gives a frame's tokens no order, roboshape/models/policy.py), but each token
made of the privileged state (roboshape/envs/state.py) instead of pixels. So it says whether a policy fails on
object tokens because they are a set or because pixels give positions too coarsely (the pick ladder,
results/small/recipe/README.md).

Tokens, in the order hand, cube, goal, distractors 0..max_distractors-1 (absent distractors all zero, which the
trunk masks out); layout float32 [DIM]:

  [0]     present    1
  [1:4]   position   x, y, z in the world frame, decimetres (the hand: the tool centre point)
  [4]     size       decimetres: the cube's half edge, a distractor's size as the state stores it; 0 for hand, goal
  [5]     opening    the finger opening in decimetres for the hand, 0 for the rest
  [6:9]   colour     what a camera tells the objects apart by: the cube's and the goal's colours (roboshape/envs/
                     palettes.py), white for the hand, one grey for every distractor; in [0, 1]

Backdrop, table and arm have no token: they do not move, or (the arm) follow the hand.
"""
import hashlib

import numpy as np

from roboshape.encoders import registry
from roboshape.envs import palettes
from roboshape.envs import state as state_lib

FIELDS = (("present", 1), ("position", 3), ("size", 1), ("opening", 1), ("colour", 3))
DIM = sum(width for _, width in FIELDS)
CUBE_HALF = 0.02                   # metres: the cube's half edge (roboshape/envs/scene.py builds it)
HAND_COLOUR = (255, 255, 255)
DISTRACTOR_COLOUR = (128, 128, 128)


def _colour(rgb) -> np.ndarray:
  return np.asarray(rgb, np.float32) / 255.0


def tokens(state, max_distractors: int):
  """float [B, state_lib.DIM] -> float32 [B, 3 + max_distractors, DIM] (layout in the module docstring), pure jnp."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  state = jnp.asarray(state, jnp.float32)
  b = state.shape[0]
  cuts = state_lib.slices()
  one, zero = jnp.ones((b, 1)), jnp.zeros((b, 1))

  def token(position, size, opening, colour, present=one):
    colour = jnp.broadcast_to(jnp.asarray(colour), (b, 3))
    return jnp.concatenate([present, 10.0 * position, 10.0 * size, 10.0 * opening, colour], -1) * present

  rows = [token(state[:, cuts["tcp_pos"]], zero, state[:, cuts["gripper"]], _colour(HAND_COLOUR)),
          token(state[:, cuts["cube_pos"]], one * CUBE_HALF, zero, _colour(palettes.CUBE_COLOR)),
          token(state[:, cuts["goal_pos"]], zero, zero, _colour(palettes.GOAL_COLOR))]
  distractors = state[:, cuts["distractors"]].reshape(b, state_lib.MAX_DISTRACTORS, 5)
  for i in range(max_distractors):
    row = distractors[:, i]
    rows.append(token(row[:, 0:3], row[:, 3:4], zero, _colour(DISTRACTOR_COLOUR), present=row[:, 4:5]))
  return jnp.stack(rows, axis=1)


def points(tokens):
  """tokens [..., N, DIM] -> (world points [..., N, 3] in metres, valid [..., N]) (FrozenEncoder.points)."""
  return tokens[..., 1:4] / 10.0, tokens[..., 0] > 0


def _step(max_distractors, params, carry, obs):
  del params
  return tokens(obs["state"], max_distractors), carry


def _build(config, workdir: str):
  """The encoder for config.env.max_distractors distractors (config None: MAX_DISTRACTORS)."""
  del workdir
  import functools  # pylint: disable=import-outside-toplevel
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  k = int(config.env.max_distractors) if config is not None else state_lib.MAX_DISTRACTORS
  layout = hashlib.sha1(f"{FIELDS} {CUBE_HALF} {HAND_COLOUR} {DISTRACTOR_COLOUR} {palettes.CUBE_COLOR} "
                        f"{palettes.GOAL_COLOR} {state_lib.describe()}".encode()).hexdigest()[:12]
  return FrozenEncoder(name="poses", params={}, step=functools.partial(_step, k), init_state=lambda batch_size: (),
                       num_tokens=3 + k, token_dim=DIM, identity=f"poses:{layout}:{k}", inputs=("state",),
                       points=points)


registry.register(registry.Kind(
    name="poses", inputs=("state",), pretrain="", build=_build, title="Poses",
    description="one token per object from the simulator's exact poses, an unordered set without ids (control: "
                "between the state token and the objects tokens)", family="control", order=5,
    tokens=lambda config: f"{3 + int(config.env.max_distractors)} x {DIM}", points=lambda config: ""))
