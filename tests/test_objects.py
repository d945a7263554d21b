"""The `objects` encoder (ground-truth object tokens from the segmentation) and the trunk's masking of absent
objects: hand-computed tokens, invariance to relabelling the ids, all-zero padding that changes nothing."""
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from configs import common
from roboshape import encoders
from roboshape.encoders import objects
from roboshape.models import policy as policy_lib

K, D = objects.NUM_IDS, objects.DIM
pytestmark = pytest.mark.usefixtures("cheap_xla_module")


def _frame():
  """A 4x4 frame: id 3 (the cube) on pixels (0, 1), (0, 2), (1, 1); id 1 (table) on row 3; the rest id 0."""
  seg = np.zeros((4, 4), np.uint8)
  seg[3] = 1
  seg[0, 1] = seg[0, 2] = seg[1, 1] = 3
  image = np.zeros((4, 4, 3), np.uint8)
  image[0, 1] = image[0, 2] = (255, 0, 0)
  image[1, 1] = (0, 0, 255)
  depth = np.full((4, 4), 2000, np.uint16)
  depth[0, 1] = depth[0, 2] = 1000
  depth[1, 1] = 1600
  return image, seg, depth


def _random_frames(rng, batch, res=8):
  image = rng.integers(0, 256, (batch, res, res, 3), dtype=np.uint8)
  seg = rng.integers(0, 9, (batch, res, res)).astype(np.uint8)            # ids 9..13 absent
  depth = rng.integers(300, 3000, (batch, res, res)).astype(np.uint16)
  return image, seg, depth


def test_tokens_of_a_hand_made_frame():
  image, seg, depth = _frame()
  tokens = np.asarray(objects.tokens(image[None], seg[None], depth[None]))[0]
  assert tokens.shape == (K, D) == (14, 12) and tokens.dtype == np.float32
  cuts = objects.slices()
  cube = tokens[3]
  # Pixel centres along a side of 4 are at -0.75, -0.25, 0.25, 0.75; the cube's rows are (0, 0, 1), cols (1, 2, 1).
  rows, cols = np.array([-0.75, -0.75, -0.25]), np.array([-0.25, 0.25, -0.25])
  np.testing.assert_allclose(cube[cuts["present"]], [1.0])
  np.testing.assert_allclose(cube[cuts["area"]], [3 / 16], rtol=1e-6)
  np.testing.assert_allclose(cube[cuts["centroid"]], [-7 / 12, -1 / 12], rtol=1e-6)
  np.testing.assert_allclose(cube[cuts["std"]], [rows.std(), cols.std()], rtol=1e-5)
  np.testing.assert_allclose(cube[cuts["half_size"]], [0.5, 0.5], rtol=1e-6)     # 2 of 4 rows, 2 of 4 cols
  np.testing.assert_allclose(cube[cuts["colour"]], [2 / 3, 0.0, 1 / 3], rtol=1e-6)
  np.testing.assert_allclose(cube[cuts["depth"]], [1.2], rtol=1e-6)              # (1 + 1 + 1.6) m / 3
  table = tokens[1]                                                               # the bottom row
  np.testing.assert_allclose(table[:8], [1, 0.25, 0.75, 0, 0, np.std([-.75, -.25, .25, .75]), 0.25, 1], rtol=1e-6,
                             atol=1e-7)
  np.testing.assert_allclose(table[cuts["depth"]], [2.0], rtol=1e-6)
  np.testing.assert_allclose(tokens[:, cuts["area"]].sum(), 1.0, rtol=1e-6)      # ids 0, 1, 3 cover the frame
  # Absent ids give all-zero tokens; without depth the depth entry is 0.
  assert not tokens[[2] + list(range(4, K))].any()
  no_depth = np.asarray(objects.tokens(image[None], seg[None]))[0]
  assert (no_depth[:, cuts["depth"]] == 0).all()
  np.testing.assert_array_equal(np.delete(no_depth, cuts["depth"], axis=1), np.delete(tokens, cuts["depth"], axis=1))


def test_relabelling_the_ids_gives_the_same_set_of_tokens():
  rng = np.random.default_rng(0)
  image, seg, depth = _random_frames(rng, batch=3)
  perm = np.arange(K)
  perm[[3, 7]] = perm[[7, 3]]                                 # swap the cube (3) and distractor 2 (7)
  perm[[0, 11]] = perm[[11, 0]]                               # an absent id (11) takes the backdrop's pixels
  perm[5:7] = rng.permutation(perm[5:7])
  relabelled = perm[seg].astype(np.uint8)
  encode = jax.jit(objects.tokens)
  tokens, moved = np.asarray(encode(image, seg, depth)), np.asarray(encode(image, relabelled, depth))
  assert not np.array_equal(tokens, moved)
  for b in range(3):                                          # the same set: equal rows once sorted
    def rows(x):
      return x[np.lexsort(x.T[::-1])]
    np.testing.assert_allclose(rows(moved[b]), rows(tokens[b]), rtol=1e-6)
  np.testing.assert_allclose(moved[:, perm], tokens, rtol=1e-6)          # row k moves to row perm[k]
  assert (tokens[:, 9:] == 0).all() and (tokens[:, :9, 0] == 1).all()


def test_the_encoder_is_registered_and_encodes_dict_batches():
  kind = encoders.get("objects")
  assert "objects" in encoders.names() and not kind.pretrain and kind.inputs == ("image", "segmentation")
  for task in common.TASKS:
    config = importlib.import_module(f"configs.{task}_objects").get_config("tiny")
    assert (config.task, config.encoder) == (task, "objects") and "pretrain" not in config.stages
  config = importlib.import_module("configs.push_objects").get_config("tiny")
  enc = encoders.build_encoder(config, "")
  # The ids of distractors the config never places are always absent: their tokens are left out.
  kept = list(objects.token_ids(config.env.max_distractors))
  assert kept == list(range(5 + config.env.max_distractors)) + [13]
  assert (enc.inputs, enc.num_tokens, enc.token_dim) == (("image", "segmentation"), len(kept), D)
  rng = np.random.default_rng(1)
  image, seg, depth = _random_frames(rng, batch=2 * 5)
  videos = dict(image=image.reshape(2, 5, 8, 8, 3), segmentation=seg.reshape(2, 5, 8, 8),
                depth=depth.reshape(2, 5, 8, 8), state=np.zeros((2, 5, 65), np.float32))
  out = np.asarray(enc.encode_batch(videos))
  assert out.shape == (2, 5, len(kept), D) and out.dtype == np.float32
  np.testing.assert_allclose(out.reshape(10, len(kept), D), objects.tokens(image, seg)[:, kept], rtol=1e-6)
  # With env.depth the encoder reads depth as well (another identity, so another feature cache).
  config.env.depth = True
  with_depth = encoders.build_encoder(config, "")
  assert with_depth.inputs == ("image", "segmentation", "depth") and with_depth.identity != enc.identity
  np.testing.assert_allclose(np.asarray(with_depth.encode_batch(videos)).reshape(10, len(kept), D),
                             objects.tokens(image, seg, depth)[:, kept], rtol=1e-6)
  np.testing.assert_allclose(np.asarray(with_depth.encode_episode({k: v[0] for k, v in videos.items()})),
                             np.asarray(with_depth.encode_batch(videos))[0], rtol=1e-6)


def test_all_zero_tokens_are_masked_out_of_the_trunk():
  config = common.get_config("push", "objects", "tiny")
  p = config.policy
  p.history, p.width, p.num_layers, p.num_heads, p.dropout = 3, 32, 2, 2, 0.0
  net = policy_lib.net_from_config(p)
  rng = np.random.default_rng(2)
  b, t = 2, 3
  image, seg, depth = _random_frames(rng, batch=b * t)
  tokens = jnp.asarray(objects.tokens(image, seg, depth)).reshape(b, t, K, D)
  frames = jnp.broadcast_to(jnp.arange(t), (b, t))
  params = jax.jit(net.init)(jax.random.PRNGKey(0), tokens, frames)
  apply = jax.jit(lambda x: net.apply(params, x, frames))

  def padded(extra):
    return jnp.concatenate([tokens, jnp.broadcast_to(extra, (b, t, 4, D))], axis=2)

  base, zeros, ones = apply(tokens), apply(padded(0.0)), apply(padded(1.0))
  for name in ("logits", "means", "scales"):
    np.testing.assert_allclose(getattr(zeros, name), getattr(base, name), atol=1e-5)
  assert not np.allclose(ones.means, base.means, atol=1e-3)            # a non-zero token does count
  # Dropping the absent ids' (all-zero) tokens altogether gives the same actions too.
  np.testing.assert_allclose(apply(tokens[:, :, :9]).means, base.means, atol=1e-5)


def test_the_mask_of_present_tokens_is_the_plain_one_and_no_row_is_empty():
  act_frames = jnp.array([[0, 2], [1, 2]])
  plain = policy_lib.attention_mask(3, 2, act_frames)
  np.testing.assert_array_equal(policy_lib.attention_mask(3, 2, act_frames, jnp.ones((2, 6), bool)), plain)
  present = jnp.zeros((2, 6), bool).at[0, 1].set(True)                  # almost every token padding
  mask = np.asarray(policy_lib.attention_mask(3, 2, act_frames, present))[:, 0]
  assert mask.any(axis=-1).all()                                        # every row keeps a key
  assert mask[:, np.arange(8), np.arange(8)].all()                      # itself, [ACT] tokens included
  assert mask[0, 6:, 1].tolist() == [True, True] and not mask[0, 6:][:, [0, 2, 3, 4, 5]].any()
  assert not mask[1, 6:, :6].any()                                      # [ACT] rows see themselves alone
