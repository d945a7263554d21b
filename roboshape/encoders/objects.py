"""`objects`: ground-truth object tokens from the segmentation, one per object id (control: SAVi's upper bound).

Each frame becomes up to NUM_IDS = 14 tokens, one per segmentation id 0..13 (roboshape/envs/ids.py: 0 floor/backdrop,
1 table, 2 robot arm, 3 the red cube, 4 the target or bin, 5 + i distractor i, 13 the robot's hand), each made only of what that id's mask shows: its area, where it
is, how large it is, its mean colour and depth. A token does not hold its id, and the trunk gives a frame's tokens
no order (roboshape/models/policy.py), so the policy sees an unordered set of objects, like SAVi's slots. An id
that is absent from the frame (its mask is empty) gives an all-zero token, which the trunk masks out as a key.

Token layout (float32 [DIM], DIM = 12; coordinates are pixel centres mapped to [-1, 1], row 0 at the top):

  [0]     present    1 if the mask is non-empty
  [1]     area       fraction of the frame's pixels in the mask
  [2:4]   centroid   mean (row, col) of the mask's pixels, in [-1, 1]
  [4:6]   std        standard deviation of the mask's (row, col), in the same units
  [6:8]   half size  half the bounding box's (height, width), pixels counted whole (one pixel: 1/H, 1/W)
  [8:11]  colour     mean RGB of the mask's pixels, in [0, 1]
  [11]    depth      mean camera depth of the mask's pixels in metres (0 without depth)

Depth. The registered Kind reads ("image", "segmentation"): the inputs every dataset stores. An encoder built for a
config with `env.depth` true (the :small variants store depth) also reads "depth" (uint16 millimetres): its
`FrozenEncoder.inputs` is ("image", "segmentation", "depth"), and the cache feeds it from the dataset. Without
depth the depth entry is 0.
"""
import functools
import hashlib

from roboshape.encoders import registry
from roboshape.envs import ids

NUM_IDS = ids.NUM_IDS   # backdrop, table, robot arm, cube, target/bin, up to 8 distractors, the hand
FIELDS = (("present", 1), ("area", 1), ("centroid", 2), ("std", 2), ("half_size", 2), ("colour", 3), ("depth", 1))
DIM = sum(width for _, width in FIELDS)


def slices():
  """{field name: slice of the token} in the order of FIELDS."""
  cuts, start = {}, 0
  for name, width in FIELDS:
    cuts[name] = slice(start, start + width)
    start += width
  return cuts


def describe() -> str:
  """The token layout, one "[start:stop] name" per field."""
  return ", ".join(f"[{s.start}:{s.stop}] {name}" for name, s in slices().items())


def _coords(size: int):
  """float32 [size]: the centres of `size` pixels along an axis, mapped to [-1, 1]."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  return (2.0 * jnp.arange(size, dtype=jnp.float32) + 1.0) / size - 1.0


def tokens(image, segmentation, depth=None):
  """One frame's object tokens, pure jnp (jit-friendly: one-hot masks, no loops over pixels or ids).

  Args:
    image: uint8 [B, H, W, 3].
    segmentation: integer [B, H, W] object ids; ids outside 0..NUM_IDS-1 belong to no token.
    depth: None, or uint16 [B, H, W] millimetres.

  Returns:
    float32 [B, NUM_IDS, DIM], row k the token of id k (all zero when id k is absent); layout in the module
    docstring.
  """
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  exact = jax.lax.Precision.HIGHEST   # no TF32 / bf16 passes on accelerators: these are sums of 0/1 weights
  h, w = segmentation.shape[-2:]
  masks = jax.nn.one_hot(segmentation, NUM_IDS, dtype=jnp.float32)              # [B, H, W, K]
  rows, cols = masks.sum(axis=2), masks.sum(axis=1)                              # [B, H, K], [B, W, K]
  count = rows.sum(axis=1)                                                       # [B, K]
  present = count > 0
  safe = jnp.maximum(count, 1.0)

  def moments(marginal, coords):
    """marginal [B, S, K] pixel counts per line, coords [S] -> mean, std, half size, each [B, K]."""
    mean = jnp.einsum("bsk,s->bk", marginal, coords, precision=exact) / safe
    var = jnp.einsum("bsk,bsk->bk", marginal, (coords[None, :, None] - mean[:, None, :]) ** 2, precision=exact)
    std = jnp.sqrt(jnp.maximum(var / safe, 0.0))
    inside = marginal > 0
    low = jnp.min(jnp.where(inside, coords[None, :, None], jnp.inf), axis=1)
    high = jnp.max(jnp.where(inside, coords[None, :, None], -jnp.inf), axis=1)
    half = jnp.where(present, 0.5 * (high - low) + 1.0 / coords.shape[0], 0.0)
    return mean, std, half

  row_mean, row_std, row_half = moments(rows, _coords(h))
  col_mean, col_std, col_half = moments(cols, _coords(w))
  colour = jnp.einsum("bhwk,bhwc->bkc", masks, jnp.asarray(image, jnp.float32) / 255.0,
                      precision=exact) / safe[..., None]                          # [B, K, 3]
  if depth is None:
    mean_depth = jnp.zeros_like(count)
  else:
    mean_depth = jnp.einsum("bhwk,bhw->bk", masks, jnp.asarray(depth, jnp.float32) / 1000.0,
                            precision=exact) / safe
  out = jnp.concatenate([
      present.astype(jnp.float32)[..., None], (count / (h * w))[..., None],
      jnp.stack([row_mean, col_mean], -1), jnp.stack([row_std, col_std], -1), jnp.stack([row_half, col_half], -1),
      colour, mean_depth[..., None]], axis=-1)                                   # [B, K, DIM]
  return jnp.where(present[..., None], out, 0.0)


def token_ids(max_distractors: int) -> tuple:
  """The ids a scene with at most `max_distractors` distractors can show, in token order: backdrop, table, arm, cube,
  goal, distractors 0..max_distractors-1, hand. The others are always absent (all-zero tokens the trunk masks out),
  so leaving them out changes no action (tests/test_objects.py) and saves the trunk their cost."""
  return tuple(range(ids.FIRST_DISTRACTOR + max_distractors)) + (ids.HAND,)


def _step(kept, params, carry, obs):
  """obs {"image": uint8 [B, H, W, 3], "segmentation": [B, H, W], ("depth": uint16 [B, H, W])} ->
  (tokens float32 [B, len(kept), DIM] of the ids `kept`, carry)."""
  del params
  return tokens(obs["image"], obs["segmentation"], obs.get("depth"))[:, list(kept)], carry


def points(tokens):
  """tokens [..., N, DIM] -> (world points [..., N, 3], valid [..., N]): each object's mask centroid at its mean
  depth, through the front camera's calibration (roboshape/envs/camera.py); valid where the object is in view and
  has a depth (FrozenEncoder.points; a mask's centroid is its pixels', not the object's centre)."""
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  cuts = slices()
  centroid, depth = tokens[..., cuts["centroid"]], tokens[..., cuts["depth"].start]
  where = camera.unproject(centroid[..., 0], centroid[..., 1], depth)
  return where, (tokens[..., cuts["present"].start] > 0) & (depth > 0)


def _build(config, workdir: str):
  """The encoder: the tokens of `token_ids(config.env.max_distractors)` (config None: every id); it reads depth too
  when `config.env.depth` is true (config None: no depth)."""
  del workdir
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  depth = bool(config is not None and config.env.depth)
  kept = token_ids(int(config.env.max_distractors)) if config is not None else tuple(range(NUM_IDS))
  inputs = ("image", "segmentation") + (("depth",) if depth else ())
  layout = hashlib.sha1(f"ids {kept}: {describe()}".encode()).hexdigest()[:12]
  return FrozenEncoder(name="objects", params={}, step=functools.partial(_step, kept),
                       init_state=lambda batch_size: (), num_tokens=len(kept), token_dim=DIM,
                       identity=f"objects:{layout}:{'+'.join(inputs)}", inputs=inputs,
                       points=points if depth else None)


registry.register(registry.Kind(
    name="objects", inputs=("image", "segmentation"), pretrain="", build=_build, title="Objects",
    description="ground-truth object tokens from the segmentation, one per id (control: the upper bound of SAVi); "
                "reads depth too with env.depth", family="control", order=4, views=True,
    tokens=lambda config: f"{len(token_ids(config.env.max_distractors))} x {DIM}",
    points=lambda config: "" if config.env.depth else (
        "its tokens place objects in 3-D only with depth: set env.depth=True (and collect the dataset with it)")))
