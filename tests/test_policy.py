"""The transformer policy: GMM density, slot-permutation invariance, causality of [ACT], BC overfitting, the feature
cache, checkpoints and the closed-loop controller (one compilation)."""
import json
import os
import shutil

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest
import scipy.stats

from configs import common
from roboshape import data as data_lib
from roboshape import encoders
from roboshape import rundir
from roboshape.errors import UserError
from roboshape.models import heads
from roboshape.models import policy as policy_lib
from roboshape.models.encoder import FrozenEncoder
from roboshape.train import bc
from roboshape.train import cache
from roboshape.train import history as history_lib

RES, K, D, H = 8, 3, 6, 4


def _toy_encoder(identity="toy-v1") -> FrozenEncoder:
  """A fixed random projection of the frame into K tokens, plus half of the previous step's tokens (recurrent)."""
  w = jax.random.normal(jax.random.PRNGKey(7), (RES * RES * 3, K * D)) / 16.0

  def step(params, state, frames):
    x = frames.reshape(frames.shape[0], -1).astype(jnp.float32) / 255.0
    tokens = jnp.tanh(x @ params["w"]).reshape(-1, K, D) + 0.5 * state
    return tokens, tokens

  # Like SAVi's, the initial state lives on a one-device mesh: the controller must not recompile for it.
  replicated = jax.sharding.NamedSharding(jax.sharding.Mesh(jax.devices()[:1], ("data",)),
                                          jax.sharding.PartitionSpec())
  return FrozenEncoder(name="toy", params={"w": w}, step=step,
                       init_state=lambda b: jax.device_put(jnp.zeros((b, K, D), jnp.float32), replicated),
                       num_tokens=K, token_dim=D, identity=identity)


def _episode(seed: int, length: int) -> dict:
  """A synthetic demo: random frames, smooth actions in [-1, 1] that depend on the frames' time."""
  rng = np.random.default_rng(seed)
  t = np.arange(length)[:, None]
  phase = rng.uniform(0, 2 * np.pi, (1, 7))
  action = (0.8 * np.sin(0.5 * t + phase)).astype(np.float32)
  action[:, 6] = np.where(t[:, 0] < length // 2, -1.0, 1.0)
  return dict(task="pick", level="train", seed=seed, success=True, env_version="test", terminated=True,
              image=rng.integers(0, 255, (length + 1, RES, RES, 3), dtype=np.uint8),
              segmentation=np.zeros((length + 1, RES, RES), np.uint8), action=action,
              reward=np.zeros((length,), np.float32))


def _config(steps=400):
  config = common.get_config("pick", "savi", "tiny")
  config.env.resolution = RES
  p = config.policy
  p.history, p.width, p.num_layers, p.num_heads, p.dropout = H, 64, 2, 2, 0.0
  p.train.update(dict(steps=steps, batch_size=16, learning_rate=3e-3, warmup_steps=10, log_every=50,
                      eval_every=steps // 2, checkpoint_every=200, val_batch_size=8))
  return config


# ----------------------------------------------------------------------------------------------------------------
# GMM head.


def test_gmm_log_prob_matches_scipy():
  logits = np.array([[0.3, -1.0, 2.0]])                                # [B=1, M=3]
  means = np.array([[[0.1, -0.2], [0.5, 0.5], [-0.7, 0.0]]])           # [1, 3, A=2]
  scales = np.array([[[0.3, 0.2], [1.0, 0.5], [0.05, 0.4]]])
  x = np.array([[-0.6, 0.1]])
  gmm = heads.GMM(jnp.asarray(logits), jnp.asarray(means), jnp.asarray(scales))
  weights = np.exp(logits[0]) / np.exp(logits[0]).sum()
  density = sum(w * scipy.stats.multivariate_normal.pdf(x[0], means[0, m], np.diag(scales[0, m] ** 2))
                for m, w in enumerate(weights))
  np.testing.assert_allclose(np.asarray(heads.gmm_log_prob(gmm, jnp.asarray(x)))[0], np.log(density), rtol=1e-5)
  np.testing.assert_allclose(np.asarray(heads.gmm_mean(gmm))[0], weights @ means[0], rtol=1e-5)
  sample = np.asarray(heads.gmm_sample(gmm, jax.random.PRNGKey(0), noise=0.0))[0]
  assert any(np.allclose(sample, means[0, m], atol=1e-6) for m in range(3))


def test_gmm_head_bounds():
  head = heads.GMMHead(action_dim=7, num_modes=5, min_scale=1e-4, hidden=8)
  x = 100.0 * jax.random.normal(jax.random.PRNGKey(0), (3, 4))
  gmm = jax.jit(lambda x: head.apply(head.init(jax.random.PRNGKey(1), x), x))(x)
  assert gmm.logits.shape == (3, 5) and gmm.means.shape == gmm.scales.shape == (3, 5, 7)
  assert float(jnp.abs(gmm.means).max()) <= 1.0 and float(gmm.scales.min()) >= np.float32(1e-4)


# ----------------------------------------------------------------------------------------------------------------
# Trunk.


@pytest.fixture(scope="module", params=[False, True], ids=["tokens", "frame_pool"])
def trunk(request):
  """The trunk over every token, and with each frame's tokens pooled into one (policy.frame_pool)."""
  net = policy_lib.PolicyNet(width=16, num_layers=2, num_heads=2, dropout=0.0, max_history=H, num_modes=2,
                             frame_pool=request.param)
  tokens = jax.random.normal(jax.random.PRNGKey(0), (2, H, K, D))
  params = jax.jit(net.init)(jax.random.PRNGKey(1), tokens, jnp.zeros((2, H), jnp.int32))
  apply = jax.jit(lambda p, x, q: net.apply(p, x, q).means)
  return params, tokens, apply


def test_slot_permutation_leaves_actions_unchanged(trunk):
  params, tokens, apply = trunk
  frames = jnp.broadcast_to(jnp.arange(H), (2, H))
  perm = np.stack([np.random.default_rng(t).permutation(K) for t in range(H)])      # a different one per frame
  permuted = tokens[:, np.arange(H)[:, None], perm]
  assert not np.allclose(permuted, tokens)
  np.testing.assert_allclose(apply(params, permuted, frames), apply(params, tokens, frames), atol=1e-5)
  # An all-zero token (an absent object) is padding: a frame's last token zeroed equals the frame without it.
  padded = tokens.at[:, :, -1].set(0.0)
  np.testing.assert_allclose(apply(params, padded, frames), apply(params, tokens[:, :, :-1], frames), atol=1e-5)


def test_slots_that_are_padding_in_every_frame_are_dropped_and_nothing_changes(trunk):
  params, tokens, apply = trunk
  frames = jnp.broadcast_to(jnp.arange(H), (2, H))
  tokens = tokens.at[:, :, 1].set(0.0).at[:, 1:, 2].set(0.0)     # slot 1 padding everywhere, slot 2 in late frames
  flat = np.asarray(tokens).reshape(2 * H, K, D)
  np.testing.assert_array_equal(bc.present_slots(flat), [0, 2])
  np.testing.assert_array_equal(bc.present_slots(flat[:, :2], flat[:1, :2] + 1.0), [0, 1])   # present in either
  slots = bc.present_slots(flat)
  np.testing.assert_allclose(apply(params, tokens[:, :, slots], frames), apply(params, tokens, frames), atol=1e-5)


def test_act_token_sees_all_history_and_no_future(trunk):
  params, tokens, apply = trunk
  grad_fn = jax.jit(jax.grad(lambda x, q: jnp.sum(apply(params, x, jnp.full((2, 1), q)) ** 2)))
  for q in range(H):
    grad = grad_fn(tokens, q)
    per_token = np.abs(np.asarray(grad)).sum(axis=(0, 3))                          # [H, K]
    assert (per_token[:q + 1] > 0).all(), q                                        # every history token counts
    assert (per_token[q + 1:] == 0).all(), q                                       # no future token does
  # A window's first q + 1 frames alone give the same read-out at q (episode starts need no padding).
  full = apply(params, tokens, jnp.full((2, 1), 1))
  np.testing.assert_allclose(apply(params, tokens[:, :2], jnp.full((2, 1), 1)), full, atol=1e-5)


# ----------------------------------------------------------------------------------------------------------------
# Cache, training, checkpoints and the controller, on a tiny synthetic dataset.


@pytest.fixture(scope="module")
def run(tmp_path_factory):
  """A workdir with 2 cached demos and a tiny policy trained on them (val = the same demos: overfitting)."""
  workdir = str(tmp_path_factory.mktemp("bc"))
  config = _config()
  episodes = [_episode(1, 12), _episode(2, 9)]
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
  rlds.write_dataset(data_lib.dataset_path(config, workdir), {"train": episodes, "val": episodes})
  encoder = _toy_encoder()
  feature_path = cache.build(config, workdir, encoder)       # through roboshape.data.reader
  with open(os.path.join(workdir, "config.json"), "w") as f:
    f.write(config.to_json())
  summary = bc.train(config, workdir, feature_path)
  return dict(workdir=workdir, config=config, episodes=episodes, encoder=encoder, features=feature_path,
              summary=summary)


def test_cached_features_equal_fresh_ones(run):
  data = cache.load_split(run["features"], "train")
  for i, episode in enumerate(run["episodes"]):
    fresh = np.asarray(run["encoder"].encode_episode(jnp.asarray(episode["image"])))
    a, b = data["offsets"][i], data["offsets"][i + 1]
    np.testing.assert_allclose(data["features"][a:b], fresh, atol=1e-6)
    np.testing.assert_array_equal(data["action"][a:b - 1], episode["action"])
  # Another encoder identity is another cache directory; the same one is found again without encoding.
  assert cache.feature_dir(run["config"], run["workdir"], _toy_encoder("toy-v2")) != run["features"]
  assert cache.feature_dir(run["config"], run["workdir"], run["encoder"]) == run["features"]


def test_tiny_policy_overfits_two_demos(run):
  with open(os.path.join(run["workdir"], "policy", "norm_stats.json")) as f:
    stats = json.load(f)
  assert stats["scale"] == [1.0] * 7 and stats["offset"] == [0.0] * 7          # actions already in [-1, 1]
  assert run["summary"]["val_action_mse"] < 0.01, run["summary"]
  assert run["summary"]["val_nll"] < -5.0, run["summary"]                        # from about +7 at init
  # The validation history holds every eval (the last equal to the summary) and its curves.
  history = history_lib.load(os.path.join(run["workdir"], "policy"), "val_metrics")
  tc = run["config"].policy.train
  assert [h["step"] for h in history] == list(range(tc.eval_every, tc.steps + 1, tc.eval_every))
  assert history[-1]["nll"] == pytest.approx(run["summary"]["val_nll"]) and history[0]["nll"] > history[-1]["nll"]
  assert os.path.isfile(os.path.join(run["workdir"], "policy", "val_metrics.png"))


def test_checkpoint_round_trip_and_resume_skips(run, capsys):
  net, params = bc.load_params(run["config"], run["workdir"], K, D)
  _, params_mid = bc.load_params(run["config"], run["workdir"], K, D, step=200)
  leaves = jax.tree.leaves(params)
  assert all(np.isfinite(np.asarray(x)).all() for x in leaves)
  assert any(not np.allclose(a, b) for a, b in zip(leaves, jax.tree.leaves(params_mid)))
  windows = bc.Windows(cache.load_split(run["features"], "val"), H, ([1.0] * 7, [0.0] * 7))
  val = bc.evaluate(bc.make_eval_step(net), params, windows, 8, 1000, [1.0] * 7)
  np.testing.assert_allclose(val["nll"], run["summary"]["val_nll"], rtol=1e-5)
  np.testing.assert_allclose(val["action_mse"], run["summary"]["val_action_mse"], rtol=1e-5)
  assert bc.train(run["config"], run["workdir"], run["features"]) == run["summary"]
  assert "skipping" in capsys.readouterr().out


def test_controller_matches_training_and_compiles_once(run, monkeypatch):
  monkeypatch.setattr(encoders, "build_encoder", lambda config, workdir: run["encoder"])
  policy = bc.load_policy(run["workdir"])
  episode = run["episodes"][0]
  policy.reset()
  actions = np.stack([policy.act(frame) for frame in episode["image"][:-1]])
  assert policy.num_traces == 1                                                  # jitted once for all 12 steps
  # Parity with the training path: step t reads out at position min(t, H-1) of the window ending at frame t.
  feats = cache.load_split(run["features"], "train")["features"]
  windows = np.stack([feats[np.clip(np.arange(H) + max(0, t - H + 1), 0, t)] for t in range(len(actions))])
  gmm = jax.jit(policy.net.apply)(policy.params, windows, np.minimum(np.arange(len(actions)), H - 1)[:, None])
  np.testing.assert_allclose(actions, np.asarray(heads.gmm_mean(gmm))[:, 0], atol=1e-5)
  mse = float(np.mean((actions - episode["action"]) ** 2))
  assert mse < 0.01, mse
  # A batch of two envs; resetting env 1 alone restarts its episode and leaves env 0's memory alone.
  other = run["episodes"][1]["image"]
  policy.reset(batch_size=2)
  out = [policy.act_batch(np.stack([episode["image"][t], other[t]])) for t in range(3)]
  policy.reset_slots([1])
  again = policy.act_batch(np.stack([episode["image"][3], other[0]]))
  np.testing.assert_allclose(again[1], out[0][1], atol=1e-5)
  np.testing.assert_allclose(again[0], actions[3], atol=1e-5)
  assert policy.num_traces == 2                                                  # one more for batch size 2


# ----------------------------------------------------------------------------------------------------------------
# Windows.


def test_windows_cover_every_action_and_target_each_positions_own():
  # Episodes of 4, 2 and 1 actions (5, 3 and 2 frames); feature value = global frame index, action = 10 x it.
  data = dict(features=np.arange(10, dtype=np.float32).reshape(10, 1, 1),
              action=np.repeat(10.0 * np.arange(10, dtype=np.float32)[:, None], 7, axis=1),
              offsets=np.array([0, 5, 8, 10]), success=np.array([True, True, True]))
  w = bc.Windows(data, history=3, normalise=([2.0] * 7, [1.0] * 7))
  assert len(w) == 2 + 1 + 1                             # T - H + 1 windows, at least one per episode
  b = w.gather(np.arange(4))
  assert b["action"].shape == (4, 3, 7) and b["mask"].shape == (4, 3)
  np.testing.assert_array_equal(b["tokens"][:, :, 0, 0], [[0, 1, 2], [1, 2, 3], [5, 6, 7], [8, 9, 9]])
  np.testing.assert_array_equal(b["action"][:, :, 0] * 2 + 1,
                                [[0, 10, 20], [10, 20, 30], [50, 60, 70], [80, 90, 90]])
  # An episode's last frame has no action, nor do the repeats of it that pad an episode shorter than H.
  np.testing.assert_array_equal(b["mask"], [[1, 1, 1], [1, 1, 1], [1, 1, 0], [1, 0, 0]])


def test_gripper_change_steps_carry_change_weight_and_nothing_else_does():
  # Two episodes of 5 frames; gripper commands (last entry) open, open, closed, closed | open, closed, closed, open.
  # The second episode's first frame differs from the first's last frame but starts an episode: not a change.
  grip = np.array([1, 1, -1, -1, -1, 1, -1, -1, 1, 1], np.float32)
  data = dict(features=np.arange(10, dtype=np.float32).reshape(10, 1, 1),
              action=np.concatenate([np.zeros((10, 6), np.float32), grip[:, None]], axis=1),
              offsets=np.array([0, 5, 10]), success=np.array([True, True]))
  np.testing.assert_array_equal(bc.gripper_changes(data["action"], data["offsets"]), [2, 6, 8])
  w = bc.Windows(data, history=5, normalise=([1.0] * 7, [0.0] * 7), change_weight=4.0)
  b = w.gather(np.arange(2))
  np.testing.assert_array_equal(b["weight"], [[1, 1, 4, 1, 0], [1, 4, 1, 4, 0]])    # the last frames: no action
  plain = bc.Windows(data, history=5, normalise=([1.0] * 7, [0.0] * 7)).gather(np.arange(2))
  np.testing.assert_array_equal(plain["weight"], plain["mask"])


def test_a_run_trained_with_action_chunks_is_refused_in_one_line_and_one_without_loads(run, tmp_path, monkeypatch):
  monkeypatch.setattr(encoders, "build_encoder", lambda config, workdir: run["encoder"])
  old = run["config"].to_dict()
  old["policy"]["chunk"], old["policy"]["eval"]["ensemble_decay"] = 1, 0.01       # a config.json of before
  old_run = str(tmp_path / "old")
  shutil.copytree(os.path.join(run["workdir"], "policy"), os.path.join(old_run, "policy"))
  with open(rundir.config_path(old_run), "w") as f:
    json.dump(old, f)
  params = bc.load_policy(old_run).params
  same = bc.load_params(run["config"], run["workdir"], K, D)[1]
  assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(same)))
  old["policy"]["chunk"] = 8
  with open(rundir.config_path(old_run), "w") as f:
    json.dump(old, f)
  with pytest.raises(UserError, match=r"old/config.json is a run trained with action chunks \(policy.chunk=8\)"):
    bc.load_policy(old_run)


_TWO_DEVICES = r'''
import sys
import jax, numpy as np
jax.config.update("jax_disable_most_optimizations", True)     # compile-bound: XLA's cheap optimisation level
from configs import common
from roboshape.models import policy as policy_lib
from roboshape.train import bc, sharding
assert jax.local_device_count() == 2, jax.devices()
pc = common.get_config("push", "savi", "tiny").policy
net, optimizer = policy_lib.net_from_config(pc), bc.make_optimizer(pc.train)
b, h, n, d = 4, pc.history, 3, 8
rng = np.random.default_rng(0)
batches = [dict(tokens=rng.normal(size=(b, h, n, d)).astype(np.float32),
                action=rng.uniform(-1, 1, (b, h, pc.action_dim)).astype(np.float32),
                mask=np.ones((b, h), np.float32)) for _ in range(3)]
step, key, dp = bc.make_train_step(net, optimizer), jax.random.PRNGKey(3), sharding.DataParallel(b, 2 * b)
assert dp.num_devices == 2 and sharding.DataParallel(3).num_devices == 1 and sharding.DataParallel(6, 3).num_devices == 1
one = bc.init_state(net, optimizer, (b, h, n, d), 0)
two = jax.device_put(one, dp.replicated)
for batch in batches:
  one, m1 = step(one, batch, key)
  placed = dp.put_batch(batch)
  assert len(placed["tokens"].addressable_shards) == 2 and placed["tokens"].addressable_shards[0].data.shape[0] == b // 2
  two, m2 = step(two, placed, key)
  for k in ("nll", "action_mse", "grad_norm"):
    np.testing.assert_allclose(float(m1[k]), float(m2[k]), rtol=1e-5)
# Adam moves a parameter by about the learning rate a step, whatever its gradient's size, so parameters whose
# gradient is ~0 may differ by float noise times that: compared to a tenth of the learning rate
lr = pc.train.learning_rate
for x, y in zip(jax.tree.leaves(one["params"]), jax.tree.leaves(two["params"])):
  np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=0.1 * lr)
print("max param change", max(float(np.abs(np.asarray(x) - np.asarray(y)).max()) for x, y in
      zip(jax.tree.leaves(one["params"]), jax.tree.leaves(bc.init_state(net, optimizer, (b, h, n, d), 0)["params"]))))
'''


def test_train_step_split_over_two_devices_equals_one_device():
  """The BC step with its batch split over two (host) devices gives the one-device step's params and loss, with the
  same dropout masks: data parallelism changes the speed, not the model."""
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
  env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=flags.strip())
  out = subprocess.run([sys.executable, "-c", _TWO_DEVICES], cwd=root, env=env, capture_output=True, text=True,
                       timeout=300, check=False)
  assert out.returncode == 0, out.stderr[-3000:]
  assert float(out.stdout.split("max param change")[1]) > 1e-4    # the steps moved the params: a real comparison
