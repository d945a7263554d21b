"""Several cameras (roboshape/encoders/views.py): one encoder run on each view, the views' tokens joined with a view
one-hot; the `wrist` column; configs refused for an encoder that reads the front view alone."""
import dataclasses
import importlib

import numpy as np
import pytest

from roboshape import encoders
from roboshape import rundir
from roboshape import stages
from roboshape.encoders import columns
from roboshape.encoders import objects
from roboshape.encoders import registry
from roboshape.encoders import views
from roboshape.envs import camera
from roboshape.errors import UserError
from roboshape.models import encoder as encoder_lib

D = objects.DIM


def _videos(rng, batch=2, length=3, res=8):
  """Front and wrist frames [batch, length, ...]; the wrist view shows ids 0..4 only, so its other tokens are absent."""
  out = {}
  for prefix, ids in (("", 9), ("wrist_", 5)):
    out[prefix + "image"] = rng.integers(0, 256, (batch, length, res, res, 3), dtype=np.uint8)
    out[prefix + "segmentation"] = rng.integers(0, ids, (batch, length, res, res)).astype(np.uint8)
    out[prefix + "depth"] = rng.integers(300, 3000, (batch, length, res, res)).astype(np.uint16)
  out["state"] = np.zeros((batch, length, 65), np.float32)
  return out


def _config(column="objects+wrist"):
  config = importlib.import_module("configs.pick_objects").get_config("tiny")
  columns.apply(config, column)
  return config


def test_each_view_is_encoded_alike_and_its_tokens_carry_its_one_hot():
  config = _config()
  assert tuple(config.env.cameras) == ("front", "wrist")
  enc = encoders.build_encoder(config, "")
  plain = encoders.build_encoder(_config("objects"), "")
  n = plain.num_tokens
  assert (enc.num_tokens, enc.token_dim) == (2 * n, D + 2)
  assert enc.inputs == ("image", "segmentation", "wrist_image", "wrist_segmentation")
  assert enc.identity == plain.identity + "+views:front+wrist"
  videos = _videos(np.random.default_rng(0))
  out = np.asarray(enc.encode_batch(videos))                                          # [B, L, 2n, D + 2]
  flat = lambda x, k: x.reshape((-1,) + x.shape[2:])[..., k]
  kept = list(objects.token_ids(config.env.max_distractors))
  front = np.asarray(objects.tokens(flat(videos["image"], slice(None)), flat(videos["segmentation"], slice(None))))
  wrist = np.asarray(objects.tokens(flat(videos["wrist_image"], slice(None)),
                                    flat(videos["wrist_segmentation"], slice(None))))
  out = out.reshape((-1,) + out.shape[2:])
  np.testing.assert_allclose(out[:, :n, :D], front[:, kept], rtol=1e-6)
  np.testing.assert_allclose(out[:, n:, :D], wrist[:, kept], rtol=1e-6)
  present = np.abs(out[..., :D]).sum(-1) > 0
  np.testing.assert_array_equal(out[:, :n, D], present[:, :n])                       # the front view's one-hot
  np.testing.assert_array_equal(out[:, n:, D + 1], present[:, n:])                   # the wrist view's
  assert not out[:, :n, D + 1].any() and not out[:, n:, D].any()
  # The wrist view shows ids 0..4 alone: its other tokens stay all zero, so the trunk masks them out.
  absent = [i for i, k in enumerate(kept) if k >= 5]
  assert absent and not out[:, n + np.asarray(absent)].any()


def test_each_view_keeps_its_own_recurrent_state():
  """A toy step whose token is the running sum of its frames' means: each view's sum is its own frames'."""
  def step(params, carry, image):
    del params
    carry = carry + image.astype(np.float32).mean(axis=(1, 2, 3))
    return carry[:, None, None], carry
  base = encoder_lib.FrozenEncoder(name="toy", params={}, step=step, init_state=lambda b: np.zeros(b, np.float32),
                                   num_tokens=1, token_dim=1, identity="toy")
  enc = views.with_views(base, ("front", "wrist"))
  videos = _videos(np.random.default_rng(1))
  out = np.asarray(enc.encode_batch(videos))                                          # [B, L, 2, 3]
  for v, key in enumerate(("image", "wrist_image")):
    expected = np.cumsum(videos[key].astype(np.float32).mean(axis=(2, 3, 4)), axis=1)
    np.testing.assert_allclose(out[:, :, v, 0], expected, rtol=1e-5)
  assert views.with_views(base, ("front",)) is base


def test_only_the_front_views_tokens_are_placed_in_the_world():
  config = _config()
  config.env.depth = True
  enc = encoders.build_encoder(config, "")
  plain = encoders.build_encoder(_config("objects"), "")
  n = plain.num_tokens
  videos = _videos(np.random.default_rng(2))
  tokens = np.asarray(enc.encode_batch(videos))[:, 0]                                 # [B, 2n, D + 2]
  where, valid = enc.points(tokens)
  front_where, front_valid = objects.points(tokens[:, :n, :D])
  np.testing.assert_allclose(np.asarray(where)[:, :n], np.asarray(front_where), rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(valid)[:, :n], np.asarray(front_valid))
  assert np.asarray(front_valid).any() and not np.asarray(valid)[:, n:].any()
  assert not np.asarray(where)[:, n:].any()


def test_the_wrist_column_reads_back_from_a_saved_config_and_has_its_own_grid_dataset():
  config = _config()
  assert columns.of_config(config) == "objects+wrist" and not columns.policy_only("objects+wrist")
  saved = config.to_dict()
  saved["env"]["cameras"] = list(saved["env"]["cameras"])                             # as config.json holds it
  assert columns.of_config(saved) == "objects+wrist"
  assert columns.of_config(_config("objects")) == "objects"
  assert rundir.grid_data_dir(config, "/w", "pick") == "/w/data/pick"
  assert rundir.grid_data_dir(config, "/w", "pick", camera.others(("front", "wrist"))) == "/w/data/pick_wrist"


def test_an_encoder_that_reads_the_front_view_alone_is_refused_with_several_cameras(monkeypatch):
  stages.check(_config())
  stages.check(_config("state+wrist"))      # reads no frames: the cameras change nothing
  savi = importlib.import_module("configs.pick_savi").get_config("tiny")
  columns.apply(savi, "savi+wrist")
  stages.check(savi)                        # pretrained on every view's clips
  monkeypatch.setitem(registry._REGISTRY, "savi", dataclasses.replace(encoders.get("savi"), views=False))
  with pytest.raises(UserError, match=r"env.cameras=.*the savi encoder reads the front view alone"):
    stages.check(savi)


def test_a_view_is_the_episode_under_the_front_cameras_names():
  episode = dict(image=1, segmentation=2, depth=3, wrist_image=4, wrist_segmentation=5, wrist_depth=6, seed=7)
  assert camera.view(episode, "wrist") == dict(image=4, segmentation=5, depth=6, seed=7)
  assert camera.view(episode, "front") == dict(image=1, segmentation=2, depth=3, seed=7)
  assert camera.view(dict(image=1, wrist_image=4), "wrist") == dict(image=4)
