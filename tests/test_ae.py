"""The `ae` encoder (roboshape/models/ae.py, trained by roboshape/train/pretrain.py): a frame autoencoder trained with
SAVi's settings and loop, frozen to one token per frame; on 16x16 synthetic clips with a 16-wide latent."""
import itertools
import json
import os

import jax
import numpy as np
import pytest

from configs import common
from roboshape import encoders
from roboshape import rundir
from roboshape import stages
from roboshape.checkpoint import Checkpointer
from roboshape.encoders import ae as ae_encoder
from roboshape.errors import UserError
from roboshape.eval import reconstruction
from roboshape.models import ae
from roboshape.train import cache
from roboshape.train import history as history_lib
from roboshape.train import pretrain

LATENT = 16
STEPS = 4


def tiny_config(steps: int = STEPS):
  """push x ae at :tiny, shrunk to 16x16 frames: five 8-channel 3x3 convs, an 8x8 grid, two 16-channel decoder
  layers, a 16-wide latent; batches of 2 clips of 6 frames; checkpoints and validation every 2 steps."""
  config = common.get_config("push", "ae", "tiny")
  config.env.resolution = 16
  config.ae.latent_size = LATENT
  a = config.ae
  a.encoder.features, a.encoder.strides, a.encoder.kernel_size = (8,) * 5, (1,) * 5, 3
  a.encoder.mlp_size, a.encoder.output_size = 16, 16
  a.decoder.features, a.decoder.strides, a.decoder.kernel_size = (16, 16), (2, 1), 3
  p = config.pretrain
  p.train.steps, p.train.batch_size, p.train.clip_length = steps, 2, 6
  p.train.learning_rate, p.train.warmup_steps = 3e-3, 2
  p.train.checkpoint_every, p.train.keep_checkpoints = 2, 3
  p.eval.every, p.eval.episodes, p.eval.frames = 2, 2, 6
  return config


def clip(seed: int, length: int = 6, size: int = 16) -> np.ndarray:
  """uint8 [length, size, size, 3]: a coloured square sliding over a grey backdrop and a darker table."""
  rng = np.random.default_rng(seed)
  video = np.full((length, size, size, 3), 128, np.uint8)
  video[:, size // 2:] = 80
  y, x = rng.integers(0, size - 5, 2)
  colour = rng.integers(0, 256, 3)
  for t in range(length):
    video[t, y:y + 5, (x + t) % (size - 5):(x + t) % (size - 5) + 5] = colour
  return video


class Source:
  """batches_from(start) for pretrain.train: batch i is fixed by i; remembers the indices it served, and stops
  with KeyboardInterrupt (a kill) when asked for batch `fail_at`."""

  def __init__(self, fail_at=None):
    self.fail_at, self.starts, self.served = fail_at, [], []

  def _batch(self, i):
    if i == self.fail_at:
      raise KeyboardInterrupt("killed")
    self.served.append(i)
    return {"video": np.stack([clip(2 * i), clip(2 * i + 1)]), "episode_seed": np.array([2 * i, 2 * i + 1])}

  def __call__(self, start):
    self.starts.append(start)
    return map(self._batch, itertools.count(start))


pytestmark = pytest.mark.usefixtures("cheap_xla_module")     # compile-bound: XLA's cheap optimisation level


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
  """STEPS steps in one run, validated on two episodes, with its workdir."""
  config = tiny_config()
  workdir = str(tmp_path_factory.mktemp("ae_run"))
  rundir.save_config(config, workdir)
  result = pretrain.train(config, workdir, Source(), [{"image": clip(100)}, {"image": clip(101)}],
                             reconstruction.validation)
  return {"config": config, "workdir": workdir, "result": result}


def _tree_equal(a, b):
  return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(np.asarray(x), np.asarray(y))), a, b)))


def test_the_model_overfits_one_clip_in_rgb_and_depth():
  """30 steps on one clip (depth weighted as at :small) take the RGB reconstruction MSE below 0.3x its first value
  (measured: 0.05x) and the depth MSE below 0.5x (0.26x: Adam moves the depth output's bias ~lr per step)."""
  config = tiny_config(steps=30)
  config.pretrain.train.depth_weight = 0.25
  comp = pretrain.compiled(config)
  video = np.stack([clip(7), clip(7)])
  depth = np.where(video[..., 0] == 80, 1000, 400).astype(np.uint16)        # the table 1 m away, the rest 0.4 m
  state = comp.init_state(jax.random.key(0), video.shape)
  key = jax.random.key(1)
  history = []
  for _ in range(30):
    state, metrics = comp.train_step(state, video, depth, None, key)
    history.append({k: float(v) for k, v in metrics.items()})
  first, last = history[0], history[-1]
  assert last["recon_mse"] < 0.3 * first["recon_mse"], (first, last)
  assert last["depth_mse"] < 0.5 * first["depth_mse"], (first, last)
  np.testing.assert_allclose(first["loss"], first["recon_mse"] + 0.25 * first["depth_mse"], rtol=1e-5)


@pytest.mark.parametrize("variant", ["small", "tiny"])
def test_the_ae_is_pretrained_as_savi_is(variant):
  """The AE and SAVi of a variant read one pretrain section (data, steps, schedule, clip, loss weights, cadence,
  seeds), and the AE's pool, frame encoder and decoder are SAVi's; so their compiled steps train alike."""
  savi_config, ae_config = (common.get_config("push", e, variant) for e in ("savi", "ae"))
  assert ae_config.pretrain.to_dict() == savi_config.pretrain.to_dict()
  assert ae_config.ae.pool == savi_config.savi.pool
  assert ae_config.ae.encoder.to_dict() == savi_config.savi.encoder.to_dict()
  decoder = savi_config.savi.decoder.to_dict()
  assert decoder.pop("rgb") in ("spatial", "slot")                     # the AE's one "slot" draws RGB per pixel
  assert ae_config.ae.decoder.to_dict() == decoder
  ae_comp, savi_comp = pretrain.compiled(ae_config), pretrain.compiled(savi_config)   # built, not yet compiled
  assert isinstance(ae_comp.model, ae.AE) and not isinstance(savi_comp.model, ae.AE)
  for step in (0, 1, 100, 5000):
    assert float(ae_comp.schedule(step)) == float(savi_comp.schedule(step))
  assert ae_comp.depth_weight == savi_comp.depth_weight == ae_config.pretrain.train.depth_weight
  assert ae_comp.model.input_pool == savi_comp.model.input_pool
  assert ae_comp.model.decoder_depth == savi_comp.model.decoder_depth == (variant == "small")


def test_the_token_width_defaults_to_savis_slot_and_must_be_positive():
  config = tiny_config()
  assert pretrain.compiled(config).model.latent_size == LATENT
  config.ae.latent_size = 0                                            # default: SAVi's slot size
  assert ae.latent_size(config) == config.savi.slot_size
  config.ae.latent_size = -1
  with pytest.raises(UserError, match="latent_size"):
    pretrain.validate_config(config)


def test_training_checkpoints_and_records_validation_under_ae(straight):
  root = rundir.pretrain_dir(straight["workdir"], "ae")
  result = straight["result"]
  assert result["step"] == STEPS and [s for s, _ in result["history"]] == list(range(1, STEPS + 1))
  entries = history_lib.load(root, "val_metrics")
  assert [e["step"] for e in entries] == [2, 4] and all(0 < e["recon_mse"] < 1 for e in entries)
  assert os.path.isfile(os.path.join(root, "val_metrics.png"))
  with Checkpointer(os.path.join(root, "checkpoints")) as ckpt:
    assert ckpt.latest_step() == STEPS


def test_two_steps_then_two_more_equal_four_straight(straight, tmp_path):
  config = straight["config"]
  rundir.save_config(config, str(tmp_path))
  with pytest.raises(KeyboardInterrupt):                               # killed after step 2's checkpoint
    pretrain.train(config, str(tmp_path), Source(fail_at=2))
  resumed = Source()
  result = pretrain.train(config, str(tmp_path), resumed)
  assert resumed.starts == [2] and resumed.served == [2, 3]
  assert result["step"] == STEPS and [s for s, _ in result["history"]] == [3, 4]
  assert _tree_equal(result["params"], straight["result"]["params"])
  again = Source(fail_at=0)                                            # already trained: no data read
  assert pretrain.train(config, str(tmp_path), again)["step"] == STEPS and not again.served


def test_the_frozen_encoder_gives_one_memoryless_token_per_frame(straight):
  enc = encoders.get("ae").build(straight["config"], straight["workdir"])
  assert (enc.name, enc.inputs, enc.num_tokens, enc.token_dim) == ("ae", ("image",), 1, LATENT)
  assert enc.identity.endswith(f"@{STEPS}") and _tree_equal(enc.params, straight["result"]["params"])
  videos = np.stack([clip(200), clip(201)])                             # [2, 6, 16, 16, 3]
  tokens = np.asarray(enc.encode_batch(videos))
  assert tokens.shape == (2, 6, 1, LATENT) and tokens.dtype == np.float32
  np.testing.assert_array_equal(tokens, np.asarray(enc.encode_batch(videos)))   # deterministic
  assert float(tokens.std(axis=1).max()) > 1e-4                                   # frames differ, so do tokens
  # No memory: a frame's token is the same whatever came before it (reversed, spliced, or alone).
  np.testing.assert_allclose(enc.encode_episode(videos[0][::-1]), tokens[0][::-1], atol=1e-6)
  spliced = np.concatenate([videos[1][:3], videos[0][3:]])
  np.testing.assert_allclose(enc.encode_episode(spliced)[3:], tokens[0, 3:], atol=1e-6)
  alone, carry = jax.jit(enc.step)(enc.params, enc.init_state(1), videos[1, 4][None])
  assert carry == () and alone.shape == (1, 1, LATENT)
  np.testing.assert_allclose(alone[0], tokens[1, 4], atol=1e-6)
  model = pretrain.compiled(straight["config"]).model
  latent = model.apply({"params": enc.params}, videos[0].astype(np.float32) / 255.0, method=ae.AE.encode)
  np.testing.assert_allclose(latent, tokens[0, :, 0], atol=1e-6)


def test_the_pretrain_and_cache_stages_run_on_a_dataset(synthetic_dataset, tmp_path):
  """launch.py's path for push_ae: the registry's pretrain stage (the one loop) on a real dataset, then the cache."""
  assert encoders.get("ae").pretrain == encoders.get("savi").pretrain == "loop"
  assert "pretrain" in common.get_config("push", "ae", "tiny").stages
  config = tiny_config()
  config.data.dir = os.path.dirname(os.path.dirname(synthetic_dataset))  # <dir>/roboshape_push/1.0.0
  config.stages = ("pretrain", "cache")
  workdir = str(tmp_path / "push_ae")
  stages.run(config, workdir)
  entries = history_lib.load(rundir.pretrain_dir(workdir, "ae"), "val_metrics")
  assert [e["step"] for e in entries] == [2, 4]
  enc = ae_encoder.load_encoder(workdir)
  features = cache.feature_dir(config, workdir, enc)
  with open(os.path.join(features, "manifest.json")) as f:
    manifest = json.load(f)
  assert (manifest["encoder"], manifest["num_tokens"], manifest["token_dim"]) == ("ae", 1, LATENT)
  assert manifest["episodes"] == {"train": 4, "val": 2}
  from roboshape.data import reader  # pylint: disable=import-outside-toplevel
  episode = next(reader.read_episodes(synthetic_dataset, "val"))
  cached = cache.load_split(features, "val")
  length = len(episode["image"])
  np.testing.assert_allclose(cached["features"][:length], enc.encode_episode(episode["image"]), atol=1e-5)


def test_seeds_train_one_ae_each_and_the_lowest_final_mse_is_served(tmp_path):
  """pretrain.train_seeds for the AE: one run per seed in ae/seed_<s>/, the lowest final validation reconstruction
  MSE selected (the evaluator's MSE replaced so the ranking is known) and served by the encoder."""
  config = tiny_config()
  config.pretrain.train_seeds = (0, 1)
  workdir = str(tmp_path / "run")
  rundir.save_config(config, workdir)
  scores = {0: 0.3, 1: 0.1}

  def make_validation(seed_config, root, model, episodes):
    real = reconstruction.validation(seed_config, root, model, episodes)

    def fake(params, step):
      return dict(real.run(params, step), recon_mse=scores[seed_config.seed])

    return pretrain.Validation(run=fake, keys=real.keys, describe=real.describe)

  episodes = [{"image": clip(100)}, {"image": clip(101)}]
  result = pretrain.train_and_select(config, workdir, lambda seed_config: (Source(), episodes), make_validation)
  root = rundir.pretrain_dir(workdir, "ae")
  assert sorted(os.listdir(root)) == ["seed_0", "seed_1", "seeds_recon_mse.png", "selected.json"]
  assert result["selected"] == 1 and result["selection"]["metric"] == "recon_mse"
  assert not _tree_equal(result["runs"][0]["params"], result["runs"][1]["params"])
  enc = ae_encoder.load_encoder(workdir)
  assert f"{os.sep}ae{os.sep}seed_1{os.sep}checkpoints@{STEPS}" in enc.identity
  assert _tree_equal(enc.params, result["runs"][1]["params"])
