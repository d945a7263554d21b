"""SAVi (roboshape/models/savi.py, roboshape/train/pretrain.py, roboshape/encoders/savi.py), its evaluator
(roboshape/eval/slots.py) and the decomposition metrics, on synthetic clips of moving coloured squares whose
segmentation ids are known: 16x16 frames, K = 3 slots of size 16."""
import functools
import itertools
import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import flax.linen as nn
import pytest

from configs import common
from roboshape import encoders
from roboshape import rundir
from roboshape import stages
from roboshape.checkpoint import Checkpointer
from roboshape.envs import ids
from roboshape.encoders import savi as savi_encoder
from roboshape.errors import UserError
from roboshape.eval import decomposition
from roboshape.eval import slots as slot_eval
from roboshape.eval import videos
from roboshape.models import layers
from roboshape.models import savi
from roboshape.train import history as history_lib
from roboshape.train import pretrain

STEPS = 30
COLORS = np.array([[230, 40, 40], [40, 200, 60], [50, 80, 230], [230, 210, 40]], np.uint8)


def synthetic_episode(seed: int, length: int = 6, size: int = 16, num_objects: int = 2, square: int = 5):
  """Squares moving in straight lines over a grey backdrop (id 0) and a darker "table" (id 1); objects are 3, 4..."""
  rng = np.random.default_rng(seed)
  image = np.full((length, size, size, 3), 128, np.uint8)
  seg = np.zeros((length, size, size), np.uint8)
  image[:, size // 2:] = 90
  seg[:, size // 2:] = 1
  pos = rng.uniform(0, size - square, (num_objects, 2))
  vel = rng.uniform(-1, 1, (num_objects, 2))
  colors = rng.permutation(len(COLORS))[:num_objects]
  for t in range(length):
    for i in range(num_objects):
      y, x = np.clip(pos[i] + t * vel[i], 0, size - square).astype(int)
      image[t, y:y + square, x:x + square] = COLORS[colors[i]]
      seg[t, y:y + square, x:x + square] = 3 + i
  return {"image": image, "segmentation": seg, "seed": seed}


def tiny_config():
  config = common.get_config("push", "savi", "tiny")
  config.env.resolution = 16
  s = config.savi
  s.num_slots, s.slot_size, s.slot_mlp_size = 3, 16, 32
  s.encoder.features, s.encoder.strides, s.encoder.kernel_size = (8,) * 5, (1,) * 5, 3
  s.encoder.mlp_size, s.encoder.output_size = 16, 16
  s.predictor.num_heads, s.predictor.mlp_size = 2, 32
  s.decoder.features, s.decoder.strides, s.decoder.kernel_size = (16, 16), (2, 1), 3
  s.eval.figure_frames = 3
  p = config.pretrain
  p.train.steps, p.train.batch_size, p.train.clip_length = STEPS, 1, 6
  p.train.learning_rate, p.train.warmup_steps = 3e-3, 5
  p.train.checkpoint_every, p.train.keep_checkpoints = 10, 2
  p.eval.every, p.eval.episodes, p.eval.frames = STEPS, 2, 6
  return config


class Source:
  """batches_from(start) for pretrain.train: one fixed clip, remembering the batch indices it served."""

  def __init__(self, clip, fail_at=None):
    self.clip, self.fail_at, self.starts, self.served = clip, fail_at, [], []

  def __call__(self, start):
    self.starts.append(start)
    for i in itertools.count(start):
      if i == self.fail_at:
        raise KeyboardInterrupt("killed")
      self.served.append(i)
      yield {"video": self.clip[None], "episode_seed": np.array([100 + i])}


pytestmark = pytest.mark.usefixtures("cheap_xla_module")     # compile-bound: XLA's cheap optimisation level


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
  """A tiny SAVi overfitted on one clip (STEPS steps), with its workdir: trained as the pretrain stage does, with
  pretrain.train_seeds = () (one run with config.seed)."""
  config = tiny_config()
  workdir = str(tmp_path_factory.mktemp("savi_run"))
  rundir.save_config(config, workdir)
  episodes = [synthetic_episode(1), synthetic_episode(2)]
  source = Source(episodes[0]["image"])
  result = pretrain.train_and_select(config, workdir, lambda c: (source, episodes), slot_eval.validation)
  comp = pretrain.compiled(config)
  return {"config": config, "workdir": workdir, "result": result, "episodes": episodes, "source": source,
          "comp": comp, "decompose": functools.partial(savi.decompose, comp.model)}


@pytest.fixture(scope="module")
def encoder(trained):
  return savi_encoder.load_encoder(trained["workdir"])


def test_a_located_savi_appends_where_each_slot_attends_and_its_depth_there(trained, encoder):
  """savi.located_step: the slots as the plain encoder gives them, then each slot's attended centre (row, col in
  [-1, 1]) and depth. With a depth that grows linearly down the frame, every located slot's depth is that line at
  its own row centroid (attention-weighted means of a linear function), which ties the two entries together."""
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  located = savi_encoder.load_encoder(trained["workdir"], located=True)
  assert (located.token_dim, located.inputs) == (encoder.token_dim + 3, ("image", "depth"))
  assert located.identity == encoder.identity + ":located"
  frames = trained["episodes"][1]["image"]
  size = frames.shape[1]
  rows = (2.0 * np.arange(size) + 1.0) / size - 1.0                                 # pixel centres in [-1, 1]
  depth = np.broadcast_to((1000.0 + 500.0 * rows)[None, :, None], frames.shape[:3]).astype(np.uint16)
  tokens = np.asarray(located.encode_episode({"image": frames, "depth": depth}))
  np.testing.assert_allclose(tokens[..., :-3], np.asarray(encoder.encode_episode(frames)), atol=1e-5)
  row, col, metres = tokens[..., -3], tokens[..., -2], tokens[..., -1]
  on = metres > 0
  assert on.mean() > 0.5 and np.all(np.abs(row[on]) <= 1) and np.all(np.abs(col[on]) <= 1)
  # depth rounds to whole millimetres per pixel; a cell averages pixels, so the line holds to about a millimetre
  np.testing.assert_allclose(metres[on], 1.0 + 0.5 * row[on], atol=2e-3)
  assert not tokens[..., -3:][~on].any()
  where, valid = located.points(tokens)
  np.testing.assert_array_equal(np.asarray(valid), on)
  np.testing.assert_allclose(np.asarray(where), np.asarray(camera.unproject(row, col, metres)), atol=1e-6)
  config = trained["config"].copy_and_resolve_references()
  config.policy.proprio = config.policy.hand_relative = True                      # savi+proprio+rel
  served = encoders.build_encoder(config, trained["workdir"])
  assert set(served.inputs) == {"image", "depth", "state"} and "+relative:" in served.identity
  from roboshape.envs import state as state_lib  # pylint: disable=import-outside-toplevel
  state = np.zeros((len(frames), state_lib.DIM), np.float32)                      # the hand at the world's origin
  relative = np.asarray(served.encode_episode({"image": frames, "depth": depth, "state": state}))
  width = encoder.token_dim + 3
  np.testing.assert_allclose(relative[:, :-1, width:width + 3], np.where(on[..., None], where / 0.1, 0), atol=1e-4)


def _tree_equal(a, b):
  return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(np.array_equal(np.asarray(x), np.asarray(y))), a, b)))


def test_slot_attention_is_equivariant_to_permuting_the_initial_slots():
  module = savi.SlotAttention(num_iterations=3, mlp_size=32)
  keys = jax.random.split(jax.random.key(0), 3)
  slots = jax.random.normal(keys[0], (2, 4, 16))
  inputs = jax.random.normal(keys[1], (2, 20, 8))
  params = jax.jit(module.init)(keys[2], slots, inputs)
  perm = jnp.array([2, 0, 3, 1])
  apply = jax.jit(module.apply)
  out = apply(params, slots, inputs)
  out_perm = apply(params, slots[:, perm], inputs)
  np.testing.assert_allclose(out_perm, out[:, perm], atol=1e-5)
  assert not np.allclose(out, slots, atol=1e-3)  # the slots did move


def _slot_attention_reference(params, slots, inputs, iterations, epsilon=1e-8):
  """Slot attention as the Slot Attention paper writes it, every input projected to a key and a value, built from
  the module's own params and Flax's LayerNorm, GRU and the MLP."""
  p = params["params"]
  norm = lambda name, x: nn.LayerNorm().apply({"params": p[name]}, x)
  inputs = norm("norm_inputs", inputs)
  keys, values = inputs @ p["key"]["kernel"], inputs @ p["value"]["kernel"]           # [B, N, D]
  size = slots.shape[-1]
  for _ in range(iterations):
    queries = norm("norm_slots", slots) @ p["query"]["kernel"] / np.sqrt(size)
    attention = jax.nn.softmax(jnp.einsum("bkd,bnd->bkn", queries, keys), axis=1)
    weights = attention / (attention.sum(-1, keepdims=True) + epsilon)
    slots, _ = nn.GRUCell(size).apply({"params": p["gru"]}, slots, weights @ values)
    slots = layers.MLP(32, size, layernorm=True, residual=True).apply({"params": p["mlp"]}, slots)
  return slots


def test_slot_attention_applies_its_key_and_value_maps_on_the_slots_side_with_the_same_result():
  keys = jax.random.split(jax.random.key(7), 3)
  slots = jax.random.normal(keys[0], (2, 4, 16))
  inputs = jax.random.normal(keys[1], (2, 30, 8))
  module = savi.SlotAttention(num_iterations=3, mlp_size=32)
  params = module.init(keys[2], slots, inputs)
  # the params of a Dense-layer slot attention: kernels [F, D] named key and value
  assert params["params"]["key"]["kernel"].shape == params["params"]["value"]["kernel"].shape == (8, 16)
  assert set(params["params"]["key"]) == {"kernel"}
  np.testing.assert_allclose(module.apply(params, slots, inputs),
                             _slot_attention_reference(params, slots, inputs, 3), atol=2e-5)


def test_a_full_grid_gives_slot_attention_a_pixel_each_and_keeps_the_decoder():
  config = tiny_config()
  config.savi.pool, config.savi.full_grid = 2, 4
  video = jnp.asarray(np.random.default_rng(0).random((1, 2, 16, 16, 3)), jnp.float32)
  model = savi.model_from_config(config)
  variables = jax.jit(model.init)({"params": jax.random.key(0), "slots": jax.random.key(1)}, video)
  out, inter = jax.jit(lambda v, x: model.apply(v, x, rngs={"slots": jax.random.key(2)}, mutable=["intermediates"]))(
      variables, video)
  attention = inter["intermediates"]["processor"]["corrector"]["attention"][-1]
  assert attention.shape[-1] == 16 * 16                      # one input per pixel of the 16x16 frame
  assert out["masks"].shape[-2:] == (8, 8)                   # the decoder still draws the pooled frame
  # pixels of one CNN cell differ only through the full-resolution path: no path, equal inputs
  frame = video[:, 0]
  features = model.apply(variables, frame, method=savi.SAVi.encode_frame)
  no_path = jax.tree.map(jnp.zeros_like, variables["params"]["fine"])
  flat = model.apply({"params": {**variables["params"], "fine": no_path}}, frame, method=savi.SAVi.encode_frame)
  cells = np.asarray(flat).reshape(1, 8, 2, 8, 2, -1)    # the CNN's 8x8 grid (pool 2, strides 1): 2x2-pixel cells
  assert np.allclose(cells, cells[:, :, :1, :, :1])
  assert not np.allclose(features, flat)
  assert savi.parameter_count(config.savi, 16) > savi.parameter_count(tiny_config().savi, 16)
  config.savi.encoder.strides = (3, 1, 1, 1, 1)
  with pytest.raises(UserError, match="savi.full_grid=4: the CNN's"):
    savi.check_config(config.savi, 16)


def test_slot_initializer_shared_mean():
  noise = jax.random.normal(jax.random.key(1), (2, 4, 8))
  module = savi.SlotInitializer(num_slots=4, slot_size=8, mean="shared")
  params = module.init(jax.random.key(0), noise)
  assert params["params"]["mean"].shape == (8,)
  at_mean = module.apply(params, jnp.zeros_like(noise))     # zero noise: the slots are the learned mean
  np.testing.assert_allclose(at_mean, jnp.broadcast_to(params["params"]["mean"], noise.shape), atol=1e-6)
  assert float(jnp.std(at_mean, axis=1).max()) == 0.0       # the same for the K slots
  scaled = module.apply({"params": {**params["params"], "log_scale": jnp.full((8,), np.log(2.0))}}, noise)
  np.testing.assert_allclose(scaled - at_mean, 2.0 * noise, atol=1e-5)
  with pytest.raises(ValueError, match="queries"):
    savi.SlotInitializer(num_slots=4, slot_size=8, mean="random").init(jax.random.key(0), noise)


def test_learned_queries_ignore_the_noise():
  module = savi.SlotInitializer(num_slots=4, slot_size=8, mean="queries")
  noise = jax.random.normal(jax.random.key(1), (2, 4, 8))
  params = module.init(jax.random.key(0), noise)
  slots = module.apply(params, noise)
  np.testing.assert_array_equal(slots, module.apply(params, 5.0 * noise + 1.0))  # the same slots for any noise
  np.testing.assert_array_equal(slots, jnp.broadcast_to(params["params"]["mean"], noise.shape))
  assert float(jnp.std(slots, axis=1).min()) > 0.1                              # K distinct queries


def test_last_iteration_gradient_is_one_iteration_from_the_detached_slots():
  """gradient="last" computes the same slots as "full"; its gradients (params and initial slots) are those of a
  single iteration started from the slots the first two iterations reached."""
  keys = jax.random.split(jax.random.key(4), 4)
  slots = jax.random.normal(keys[0], (2, 4, 16))
  inputs = jax.random.normal(keys[1], (2, 20, 8))
  weights = jax.random.normal(keys[2], (2, 4, 16))
  full, last, two, one = (savi.SlotAttention(num_iterations=n, mlp_size=32, gradient=g)
                          for n, g in ((3, "full"), (3, "last"), (2, "full"), (1, "full")))
  params = full.init(keys[3], slots, inputs)

  def grads(module, start):
    return jax.grad(lambda p, s: jnp.sum(weights * module.apply(p, s, inputs)), argnums=(0, 1))(params, start)

  np.testing.assert_allclose(last.apply(params, slots, inputs), full.apply(params, slots, inputs), atol=1e-6)
  reached = two.apply(params, slots, inputs)
  (p_last, s_last), (p_one, s_one), (p_full, _) = grads(last, slots), grads(one, reached), grads(full, slots)
  np.testing.assert_allclose(s_last, s_one, atol=1e-5)
  for a, b in zip(jax.tree.leaves(p_last), jax.tree.leaves(p_one)):
    np.testing.assert_allclose(a, b, atol=1e-5)
  assert max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(p_last), jax.tree.leaves(p_full))) > 1e-3
  with pytest.raises(ValueError, match="full"):
    savi.SlotAttention(num_iterations=3, mlp_size=32, gradient="implicit").init(keys[3], slots, inputs)


def test_an_identity_initialised_predictor_starts_as_layernorm():
  slots = 3.0 * jax.random.normal(jax.random.key(2), (2, 5, 16)) + 1.0
  mean = slots.mean(-1, keepdims=True)
  normalised = (slots - mean) / jnp.sqrt(((slots - mean) ** 2).mean(-1, keepdims=True) + 1e-6)
  for identity_init in (True, False):
    block = layers.TransformerBlock(num_heads=4, mlp_size=32, identity_init=identity_init)
    out = block.apply(block.init(jax.random.key(3), slots), slots)
    if identity_init:  # each slot keeps its own content, normalised
      np.testing.assert_allclose(out, normalised, atol=1e-4)
    else:              # a random attention and MLP move the slots away from it
      assert float(jnp.abs(out - normalised).max()) > 0.1

# SAVi-S (savi_conditional_small with learned-Gaussian first slots) has 853,028; :paper adds a fifth encoder conv
# (25,632) and 2 more coordinate channels in the two position embeddings (320) (configs/common.py:savi_config).
PAPER_PARAMETERS = 878_980


def test_the_paper_savi_has_savi_s_size_and_transposed_conv_decoder():
  c = common.get_config("pick", "savi", "paper")
  r = int(c.env.resolution)
  assert savi.parameter_count(c.savi, r) == PAPER_PARAMETERS
  model = savi.build_model(c.savi, r)
  video = jax.ShapeDtypeStruct((1, 1, r, r, 3), jnp.float32)
  params = jax.eval_shape(lambda v: model.init({"params": jax.random.key(0), "slots": jax.random.key(1)}, v),
                          video)["params"]
  kernels = [params["decoder"][f"up{i}"]["conv"]["kernel"].shape for i in range(4)]
  assert kernels == [(5, 5, 128, 64)] + [(5, 5, 64, 64)] * 3     # a sub-pixel layer's would have 4 x 64 outputs
  slots = jax.ShapeDtypeStruct((1, c.savi.num_slots, c.savi.slot_size), jnp.float32)
  jaxpr = jax.make_jaxpr(lambda p, s: model.apply({"params": p}, s, method=savi.SAVi.decode))(params, slots)
  convs = [e.params["lhs_dilation"] for e in jaxpr.eqns if e.primitive.name == "conv_general_dilated"]
  assert convs == [(2, 2)] * 3 + [(1, 1)]                        # transposed (input-dilated) stride-2 convs
  assert "mlp" not in params["processor"]["corrector"]           # SAVi-S's corrector: GRU, no MLP


def test_the_paper_clip_on_the_mean_loss_gives_savis_updates_on_the_summed_loss():
  """SAVi clips at 0.05 the gradient of its loss summed over a clip's N pixel values (Adam eps 1e-8); :paper's loss
  is the mean, so the same updates need the clip and Adam's epsilon divided by N: :paper states 0.05 on the sum."""
  c = common.get_config("pick", "savi", "paper")
  side = int(c.env.resolution) // int(c.savi.pool)
  n = int(c.pretrain.train.clip_length) * side * side * 3
  assert pretrain.values_per_clip(c, c.savi.pool) == n == 6 * 64 * 64 * 3
  assert (c.pretrain.train.clip_norm, c.pretrain.train.clip_norm_of) == (0.05, "sum")
  assert pretrain.clip_norm(c.pretrain.train, n) == 0.05 / (6 * 64 * 64 * 3)    # :paper's clip on the mean, as ever
  other = c.copy_and_resolve_references()          # a longer clip of smaller frames: still 0.05 on the summed loss
  other.pretrain.train.clip_length, other.env.resolution = 12, 32
  assert pretrain.clip_norm(other.pretrain.train, pretrain.values_per_clip(other, 1)) == 0.05 / (12 * 32 * 32 * 3)
  savi_train = c.pretrain.train.copy_and_resolve_references()
  savi_train.clip_norm_of = "mean"                               # SAVi's own: 0.05 on the loss it minimises, the sum
  ours, theirs = pretrain.make_optimizer(c.pretrain.train, n), pretrain.make_optimizer(savi_train, n)
  rng = np.random.default_rng(0)
  params = {"w": jnp.zeros((50, 40)), "b": jnp.zeros((40,))}
  ours_state, theirs_state = ours.init(params), theirs.init(params)
  for step, norm in enumerate((3.0, 0.01, 50.0, 0.001)):         # of the summed loss's gradient: clipped or not
    g_sum = jax.tree.map(lambda p: jnp.asarray(rng.normal(size=p.shape), jnp.float32), params)
    g_sum = jax.tree.map(lambda g: g * norm / float(jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree.leaves(g_sum)))),
                         g_sum)
    g_mean = jax.tree.map(lambda g: g / n, g_sum)
    u_ours, ours_state = ours.update(g_mean, ours_state, params)
    u_theirs, theirs_state = theirs.update(g_sum, theirs_state, params)
    if step:                                                     # step 0: the warmup's learning rate is 0
      assert float(jnp.abs(u_theirs["w"]).max()) > 0
    for a, b in zip(jax.tree.leaves(u_ours), jax.tree.leaves(u_theirs)):
      np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-12)


def test_a_tiny_model_overfits_one_clip(trained):
  history = trained["result"]["history"]
  assert [s for s, _ in history] == list(range(1, STEPS + 1))
  first, last = history[0][1], history[-1][1]
  assert last <= first / 10, (first, last)


def _tensorboard_scalars(logdir):
  """{tag: [(step, value), ...]} of the event files in `logdir` (oldest first), read back record by record: a length
  (uint64), its checksum, an Event proto, its checksum."""
  import struct  # pylint: disable=import-outside-toplevel
  from tensorboardX.proto import event_pb2  # pylint: disable=import-outside-toplevel
  scalars = {}
  for name in sorted(os.listdir(logdir)):
    with open(os.path.join(logdir, name), "rb") as f:
      data = f.read()
    at = 0
    while at < len(data):
      (size,) = struct.unpack("<Q", data[at:at + 8])
      event = event_pb2.Event.FromString(data[at + 12:at + 12 + size])
      at += 12 + size + 4
      for value in event.summary.value:
        scalars.setdefault(value.tag, []).append((event.step, value.simple_value))
  return scalars


def test_training_writes_tensorboard_and_the_decomposition_figure(trained):
  root = rundir.pretrain_dir(trained["workdir"], "savi")
  assert os.path.isfile(os.path.join(root, "figures", f"step_{STEPS:07d}.png"))
  (step, metrics), = trained["result"]["eval"]
  assert step == STEPS and -1 <= metrics["fg_ari"] <= 1 and 0 <= metrics["miou"] <= 1
  logged, losses = _tensorboard_scalars(os.path.join(root, "tb")), dict(trained["result"]["history"])
  assert [s for s, _ in logged["train/loss"]] == list(range(1, STEPS + 1))          # log_every 1 in :tiny
  np.testing.assert_allclose([v for _, v in logged["train/loss"]], [losses[s] for s in range(1, STEPS + 1)],
                             rtol=1e-6)
  assert logged["val/fg_ari"] == [(STEPS, pytest.approx(metrics["fg_ari"]))]
  (entry,) = history_lib.load(root, "val_metrics")
  assert entry["step"] == STEPS and entry["fg_ari"] == metrics["fg_ari"] and entry["train_seconds"] > 0
  assert os.path.isfile(os.path.join(root, "val_metrics.png"))


def test_validation_history_replaces_results_a_resumed_run_redoes(tmp_path):
  root = str(tmp_path)
  for step, ari in ((100, 0.1), (200, 0.2), (300, 0.3)):
    history_lib.record(root, "h", step, {"fg_ari": ari, "miou": ari / 2}, step, keys=("fg_ari", "miou"),
                       ylim=(None, 1.0))
  assert history_lib.seconds_at(root, "h", 250) == 200
  history = history_lib.record(root, "h", 200, {"fg_ari": 0.25, "miou": float("nan")}, 190, keys=("fg_ari", "miou"),
                               ylim=(None, 1.0))
  assert [(h["step"], h["fg_ari"]) for h in history] == [(100, 0.1), (200, 0.25)]
  assert [(h["step"], h["fg_ari"]) for h in history_lib.load(root, "h")] == [(100, 0.1), (200, 0.25)]
  assert os.path.getsize(os.path.join(root, "h.png")) > 1000


def test_masks_sum_to_one_per_pixel(trained):
  video = trained["episodes"][1]["image"][None]
  out = trained["decompose"](trained["result"]["params"], video)
  assert out["masks"].shape == (1, 6, 3, 16, 16)
  np.testing.assert_allclose(out["masks"].sum(axis=2), 1.0, atol=1e-5)
  recon = (out["masks"][..., None] * out["rgb"]).sum(axis=2)
  np.testing.assert_allclose(out["recon"], recon, atol=1e-5)


def test_checkpoint_round_trip_gives_identical_outputs(trained, encoder):
  params = trained["result"]["params"]
  assert _tree_equal(params, encoder.params)
  video = trained["episodes"][1]["image"][None]
  before = trained["decompose"](params, video)
  after = trained["decompose"](encoder.params, video)
  for key in ("slots", "recon", "masks"):
    np.testing.assert_array_equal(np.asarray(before[key]), np.asarray(after[key]))
  assert encoder.num_tokens == 3 and encoder.token_dim == 16 and encoder.identity.endswith(f"@{STEPS}")


def test_step_form_equals_the_video_model(trained, encoder):
  videos = np.stack([e["image"] for e in trained["episodes"]])
  reference = np.concatenate([trained["decompose"](encoder.params, v[None])["slots"] for v in videos])
  assert reference.shape == (2, 6, 3, 16)                                           # [B, T, K, D], scanned
  one = encoder.encode_episode(videos[1])                                           # [T, K, D]
  np.testing.assert_allclose(one, reference[1], atol=1e-5)
  state, step = encoder.init_state(2), jax.jit(encoder.step)
  for t in range(videos.shape[1]):                                                  # closed-loop form
    tokens, state = step(encoder.params, state, videos[:, t])
    np.testing.assert_allclose(tokens, reference[:, t], atol=1e-5)


def test_resume_continues_at_the_saved_step_with_the_same_data(trained, tmp_path):
  config, clip = trained["config"], trained["episodes"][0]["image"]
  rundir.save_config(config, str(tmp_path))
  killed = Source(clip, fail_at=25)
  with pytest.raises(KeyboardInterrupt):
    pretrain.train(config, str(tmp_path), killed)
  resumed = Source(clip)
  result = pretrain.train(config, str(tmp_path), resumed)
  assert resumed.starts == [20] and resumed.served == list(range(20, STEPS))
  assert result["step"] == STEPS and [s for s, _ in result["history"]] == list(range(21, STEPS + 1))
  assert _tree_equal(result["params"], trained["result"]["params"])
  again = Source(clip, fail_at=0)  # already trained: skips without reading data
  assert pretrain.train(config, str(tmp_path), again)["step"] == STEPS and not again.served


def test_a_full_disk_while_pretraining_is_one_line_and_the_run_resumes_to_the_same_params(trained, tmp_path,
                                                                                         monkeypatch, caplog):
  """The disk fills while checkpoint 20 is saved (in orbax's threads, which raise it at the next save): one DiskFull
  line naming the pretrain stage and the checkpoint folder, as stages.run says it; step 10 is what restores, and
  the same command resumes there and ends with the params of a run that never stopped."""
  import logging  # pylint: disable=import-outside-toplevel
  from conftest import fill_disk_at_checkpoint  # pylint: disable=import-outside-toplevel
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  from roboshape.errors import DiskFull  # pylint: disable=import-outside-toplevel
  config, clip, workdir = trained["config"], trained["episodes"][0]["image"], str(tmp_path)
  ckpt_dir = os.path.join(workdir, "savi", "checkpoints")
  with monkeypatch.context() as full:
    fill_disk_at_checkpoint(full, 20)
    with pytest.raises(DiskFull) as e:
      with stages.disk_full_is_one_line("the pretrain stage", workdir):
        pretrain.train(config, workdir, Source(clip))
  assert str(e.value).startswith(f"disk full while the pretrain stage wrote {ckpt_dir}: what it wrote completely "
                                 "is kept. Free some space on that disk") and "\n" not in str(e.value)
  assert not [r for r in caplog.records if r.levelno >= logging.ERROR]           # orbax's threads said nothing
  with Checkpointer(ckpt_dir) as ckpt:
    assert ckpt.all_steps() == [10]
  resumed = Source(clip)
  result = pretrain.train(config, workdir, resumed)
  assert resumed.starts == [10] and result["step"] == STEPS
  assert _tree_equal(result["params"], trained["result"]["params"])
  assert [s for s, _ in _tensorboard_scalars(os.path.join(workdir, "savi", "tb"))["train/loss"]] == (
      list(range(1, STEPS + 1)) + list(range(11, STEPS + 1)))      # both runs' files, none overwritten


def test_a_non_finite_loss_stops_naming_step_and_seeds(trained, tmp_path, monkeypatch):
  comp, config = trained["comp"], trained["config"]
  real = comp.train_step

  def poisoned(state, *inputs):
    new_state, metrics = real(state, *inputs)
    if int(state["step"]) == 15:
      metrics = dict(metrics, loss=jnp.float32(np.nan))
    return new_state, metrics

  monkeypatch.setattr(comp, "train_step", poisoned)
  with pytest.raises(UserError, match=r"^pretrain: the SAVi loss is nan at step 16 \(batch 15, episode seeds \[115\]\)"
                                        r".*the last checkpoint, step 10, is finite and kept"):
    pretrain.train(config, str(tmp_path), Source(trained["episodes"][0]["image"]))
  with Checkpointer(str(tmp_path / "savi" / "checkpoints")) as ckpt:
    assert ckpt.latest_step() == 10


def test_a_slot_colour_decoder_paints_each_slot_one_colour():
  """rgb="slot": each slot's RGB is one colour over the image, a linear map of the slot; only the masks are spatial."""
  slots = jax.random.normal(jax.random.key(5), (2, 3, 16))
  decoder = savi.SpatialBroadcastDecoder(grid_size=4, features=(8, 8), kernel_size=3, strides=(2, 1), rgb="slot")
  params = decoder.init(jax.random.key(6), slots)
  out = decoder.apply(params, slots)
  assert out["rgb"].shape == (2, 3, 8, 8, 3) and out["masks"].shape == (2, 3, 8, 8)
  colour = params["params"]["colour"]
  np.testing.assert_allclose(out["rgb"], jnp.broadcast_to((slots @ colour["kernel"] + colour["bias"])[:, :, None, None],
                                                          out["rgb"].shape), atol=1e-5)
  assert float(jnp.std(out["masks"], axis=(2, 3)).min()) > 0.0        # the masks still vary over the image
  np.testing.assert_allclose(out["recon"], jnp.einsum("bkhw,bkhwc->bhwc", out["masks"], out["rgb"]), atol=1e-5)
  with pytest.raises(ValueError, match="spatial"):
    savi.SpatialBroadcastDecoder(grid_size=4, features=(8,), kernel_size=3, strides=(2,), rgb="pixel").init(
        jax.random.key(6), slots)


def test_a_depth_decoder_mixes_each_slots_depth_by_the_masks():
  """depth=True adds one output per slot and pixel, mixed by the masks; the rest of the decoder is unchanged."""
  slots = jax.random.normal(jax.random.key(5), (2, 3, 16))
  kwargs = dict(grid_size=4, features=(8, 8), kernel_size=3, strides=(2, 1), rgb="slot")
  params = savi.SpatialBroadcastDecoder(**kwargs, depth=True).init(jax.random.key(6), slots)
  out = savi.SpatialBroadcastDecoder(**kwargs, depth=True).apply(params, slots)
  assert out["slot_depth"].shape == (2, 3, 8, 8) and out["depth"].shape == (2, 8, 8)
  np.testing.assert_allclose(out["depth"], jnp.sum(out["masks"] * out["slot_depth"], axis=1), atol=1e-6)
  without = {"params": {k: v for k, v in params["params"].items() if k != "depth"}}
  plain = savi.SpatialBroadcastDecoder(**kwargs).apply(without, slots)
  assert "depth" not in plain
  for key in ("recon", "masks", "rgb"):
    np.testing.assert_array_equal(plain[key], out[key])


def _forward(comp, params, video, key):
  """The model's outputs on `video` (uint8 [B, L, H, W, 3]) with slot noise `key`: one compiled call (run op by op,
  the forward compiles each of its many small operations apart)."""
  apply = jax.jit(lambda p, v, k: comp.model.apply({"params": p}, savi.to_float(v), rngs={"slots": k}))
  return apply(params, video, key)


def test_a_depth_weighted_train_step_adds_the_depth_mse_and_learns_depth():
  """loss = recon MSE + depth_weight * depth MSE (metres), the depth MSE as computed by hand, and it falls on one clip."""
  config = tiny_config()
  config.pretrain.train.depth_weight = 0.5
  comp = pretrain.compiled(config)
  video = synthetic_episode(3)["image"][None]
  depth = (400 + 600 * (synthetic_episode(3)["segmentation"] == 1)).astype(np.uint16)[None]  # table 1 m, rest 0.4 m
  key = jax.random.key(2)
  state = comp.init_state(jax.random.key(1), video.shape)
  new_state, metrics = comp.train_step(state, video, depth, None, key)
  out = _forward(comp, state["params"], video, jax.random.fold_in(key, 0))
  want = float(np.mean((np.asarray(out["depth"]) - depth / 1000.0) ** 2))
  np.testing.assert_allclose(float(metrics["depth_mse"]), want, rtol=1e-4)
  np.testing.assert_allclose(float(metrics["loss"]), float(metrics["recon_mse"]) + 0.5 * want, rtol=1e-5)
  for _ in range(25):
    new_state, last = comp.train_step(new_state, video, depth, None, key)
  assert float(last["depth_mse"]) < 0.3 * want


def test_mask_weights_make_each_segment_weigh_its_share_to_the_power():
  """A 4x4 frame: table 11 pixels, cube 3, arm 1 and hand 1 (one segment of 2: the robot counts as one)."""
  seg = np.full((4, 4), ids.TABLE, np.uint8)
  seg[0, :3] = ids.CUBE
  seg[3, 2], seg[3, 3] = ids.ROBOT, ids.HAND
  w = pretrain.mask_weights(seg[None], 1.0)[0]
  assert w.shape == (4, 4) and abs(float(w.mean()) - 1.0) < 1e-6
  for segment in (seg == ids.TABLE, seg == ids.CUBE, (seg == ids.ROBOT) | (seg == ids.HAND)):
    np.testing.assert_allclose(w[segment].sum(), 16 / 3, rtol=1e-6)    # power 1: each segment the same total
  np.testing.assert_allclose(pretrain.mask_weights(seg[None], 0.0)[0], np.ones((4, 4)))
  half = pretrain.mask_weights(seg[None], 0.5)[0]
  np.testing.assert_allclose(half[0, 0] / half[1, 1], np.sqrt(11 / 3), rtol=1e-6)   # a cube pixel over a table one


def test_a_mask_weighted_train_step_minimises_the_weighted_mse():
  """loss = the mean of the pooled pixel weights x squared errors; recon_mse stays the plain MSE."""
  config = tiny_config()
  config.pretrain.train.mask_weight = 1.0
  comp = pretrain.compiled(config)
  episode = synthetic_episode(3)
  video = episode["image"][None]
  weight = pretrain.mask_weights(episode["segmentation"][None], 1.0)
  key = jax.random.key(2)
  state = comp.init_state(jax.random.key(1), video.shape)
  _, metrics = comp.train_step(state, video, None, None, key, weight)
  out = _forward(comp, state["params"], video, jax.random.fold_in(key, 0))
  frames = np.asarray(savi.pool_frames(video.astype(np.float32) / 255.0, comp.model.input_pool))
  pooled = np.asarray(savi.pool_frames(weight[..., None], comp.model.input_pool))
  error = (np.asarray(out["recon"]) - frames) ** 2
  np.testing.assert_allclose(float(metrics["loss"]), float(np.mean(pooled * error)), rtol=1e-4)
  np.testing.assert_allclose(float(metrics["recon_mse"]), float(np.mean(error)), rtol=1e-4)
  assert not np.isclose(float(metrics["loss"]), float(metrics["recon_mse"]), rtol=1e-3)


def test_a_depth_weight_without_depth_in_the_data_is_a_user_error(tmp_path):
  config = tiny_config()
  config.pretrain.train.depth_weight = 1.0
  with pytest.raises(UserError, match="env.depth=True"):
    pretrain.train(config, str(tmp_path), Source(synthetic_episode(1)["image"]))


def test_a_learned_position_decoder_is_a_per_pixel_map_of_slot_and_cell():
  """position="learned" with 1x1 layers: each pixel's output depends on its slot and its own cell's vector only, so
  permuting the cells' vectors permutes the output pixels the same way, and each cell's masks follow a Dense stack."""
  slots = jax.random.normal(jax.random.key(5), (2, 3, 16))
  decoder = savi.SpatialBroadcastDecoder(grid_size=4, features=(8, 8), kernel_size=1, strides=(1, 1), rgb="slot",
                                         position="learned")
  params = decoder.init(jax.random.key(6), slots)["params"]
  assert params["position"].shape == (4, 4, 8) and params["up0"]["conv"]["kernel"].shape == (8, 8)   # Dense, not Conv
  out = decoder.apply({"params": params}, slots)
  order = np.random.default_rng(0).permutation(16)
  shuffled = dict(params, position=params["position"].reshape(16, 8)[order].reshape(4, 4, 8))
  moved = decoder.apply({"params": shuffled}, slots)
  np.testing.assert_allclose(moved["masks"].reshape(2, 3, 16), out["masks"].reshape(2, 3, 16)[..., order], atol=1e-6)
  dense = lambda p, x: x @ p["kernel"] + p["bias"]                    # pylint: disable=unnecessary-lambda-assignment
  x = dense(params["project"], slots)[:, :, None, :] + params["position"].reshape(1, 1, 16, 8)  # [B, K, cells, 8]
  for layer in ("up0", "up1"):
    x = jax.nn.relu(dense(params[layer]["conv"], x))
  alpha = dense(params["output"], x)[..., 0]                          # [B, K, cells]
  np.testing.assert_allclose(out["masks"].reshape(2, 3, 16), jax.nn.softmax(alpha, axis=1), atol=1e-5)
  with pytest.raises(ValueError, match="coords"):
    savi.SpatialBroadcastDecoder(grid_size=4, features=(8,), kernel_size=1, strides=(1,), position="fourier").init(
        jax.random.key(6), slots)


def test_bad_resolution_is_a_user_error():
  config = tiny_config()
  config.env.resolution = 24                     # 24 = 12 * 2: the automatic grid fits
  pretrain.validate_config(config)
  config.env.resolution = 25
  with pytest.raises(UserError, match="grid_size"):
    pretrain.validate_config(config)
  for field, bad in (("init_mean", "random"), ("slot_gradient", "implicit"), ("decoder.rgb", "pixel"),
                     ("decoder.position", "fourier")):
    broken = tiny_config()
    common.override(broken, f"savi.{field}={bad!r}")
    with pytest.raises(UserError, match=f"savi.{field}='{bad}': use one of"):
      pretrain.validate_config(broken)
  broken = tiny_config()
  common.override(broken, "savi.num_iterations=0")
  with pytest.raises(UserError, match="savi.num_iterations=0: use an int >= 1"):
    pretrain.validate_config(broken)
  broken = tiny_config()
  broken.pretrain.train.depth_weight = -0.5          # the pretrain section's ranges: checked before any stage
  with pytest.raises(UserError, match="pretrain.train.depth_weight=-0.5: use a number >= 0"):
    stages.check(broken)


def test_pool_frames_known_values():
  frames = np.arange(2 * 4 * 4 * 1, dtype=np.float32).reshape(2, 4, 4, 1)
  pooled = np.asarray(savi.pool_frames(frames, 2))
  assert pooled.shape == (2, 2, 2, 1)
  assert pooled[0, 0, 0, 0] == pytest.approx((0 + 1 + 4 + 5) / 4)
  assert pooled[1, 1, 1, 0] == pytest.approx((26 + 27 + 30 + 31) / 4)
  np.testing.assert_array_equal(savi.pool_frames(frames, 1), frames)


def test_a_pooled_model_is_evaluated_at_the_segmentation_resolution(tmp_path):
  config = tiny_config()
  config.savi.pool = 2
  pretrain.validate_config(config)
  comp = pretrain.compiled(config)
  state = comp.init_state(jax.random.key(0), (1, 6, 16, 16, 3))
  params = state["params"]
  video = synthetic_episode(3)["image"]
  out = savi.decompose(comp.model, params, video[None])
  assert out["masks"].shape == (1, 6, 3, 8, 8) and out["recon"].shape == (1, 6, 8, 8, 3)
  # The evaluation videos show the 8x8 reconstruction and slots at the frames' 16x16, beside the frames.
  rundir.save_config(config, str(tmp_path))
  with Checkpointer(rundir.checkpoints(rundir.pretrain_dir(str(tmp_path), "savi"))) as ckpt:
    ckpt.save(1, state)
  panels = videos.SaviSlotVideo(str(tmp_path), pad_multiple=8)(video)
  assert panels.shape == (6, 16, 16 * (2 + 3) + 2 * (1 + 3), 3)
  recon_panel = panels[:, :, 18:34].astype(np.float32) / 255.0
  expected = np.clip(np.asarray(out["recon"][0]), 0, 1).repeat(2, axis=1).repeat(2, axis=2)
  np.testing.assert_allclose(recon_panel, expected, atol=1 / 255 + 1e-6)
  # An oracle whose 8x8 masks are the segmentation's 2x2 blocks scores FG-ARI 1 at 16x16 and reconstructs the pooled
  # frames exactly: the evaluation repeats each mask pixel 2x2 and compares the recon with the pooled frames.
  seg = np.zeros((6, 16, 16), np.uint8)
  seg[:, 8:] = 1
  seg[:, 2:6, 4:8], seg[:, 10:14, 2:6] = 3, 4
  small = seg[:, ::2, ::2]
  masks = np.moveaxis(np.eye(3)[np.array([0, 0, 0, 1, 2])[small]], -1, 1)  # ids 0, 1 -> slot 0; 3 -> 1; 4 -> 2
  frames = np.repeat(np.repeat(video[:, ::2, ::2], 2, axis=1), 2, axis=2)   # constant 2x2 blocks
  pooled = frames[:, ::2, ::2].astype(np.float32) / 255.0

  def oracle(_, clip, first_segmentation):
    return {"masks": masks[None], "recon": pooled[None], "rgb": np.repeat(pooled[None, :, None], 3, axis=2)}

  result = slot_eval.evaluate(oracle, None, [{"image": frames, "segmentation": seg}], frames=6, pool=2)
  assert result["fg_ari"] == pytest.approx(1.0)
  assert result["recon_mse"] == pytest.approx(0.0, abs=1e-10)
  # each task object in view has a slot of its own; the hand is in no frame
  assert (result["cube_iou"], result["cube_found"], result["goal_iou"]) == (1.0, 1.0, 1.0)
  assert np.isnan(result["hand_iou"])
  config.savi.pool = 3
  with pytest.raises(UserError, match="savi.pool"):
    pretrain.validate_config(config)


def test_each_views_metrics_are_over_its_own_episodes():
  # One oracle decomposition scored against two views of an episode: the front view's segmentation is the
  # oracle's masks, the wrist view's moves the cube to where the oracle has no slot for it.
  front = np.zeros((4, 8, 8), np.uint8)
  front[:, 4:] = 1
  front[:, 1:3, 1:3] = 3
  wrist = front.copy()
  wrist[:, 1:3, 1:3] = 0
  wrist[:, 5:7, 5:7] = 3
  masks = np.moveaxis(np.eye(2)[(front == 3).astype(int)], -1, 1)        # slot 1 is the front view's cube
  image = np.zeros((4, 8, 8, 3), np.uint8)

  def oracle(_, clip, first_segmentation):
    return {"masks": masks[None], "recon": np.zeros((1, 4, 8, 8, 3)), "rgb": np.zeros((1, 4, 2, 8, 8, 3))}

  views = [{"image": image, "segmentation": front}, {"image": image, "segmentation": wrist}]
  result = slot_eval.evaluate(oracle, None, views, frames=4, views=("front", "wrist"))
  assert (result["cube_iou_front"], result["cube_found_front"]) == (1.0, 1.0)
  # the wrist view's cube (4 pixels) lies inside the other slot (the frame's 60 other pixels)
  assert (result["cube_iou_wrist"], result["cube_found_wrist"]) == (pytest.approx(4 / 60), 0.0)
  # the pooled figures are over both views' frames, as without `views`
  assert (result["cube_iou"], result["cube_found"]) == (pytest.approx((1 + 4 / 60) / 2), 0.5)
  assert result["fg_ari"] == pytest.approx((result["fg_ari_front"] + result["fg_ari_wrist"]) / 2)
  plain = slot_eval.evaluate(oracle, None, views, frames=4)
  assert {k: result[k] for k in plain} == pytest.approx(plain, nan_ok=True)
  assert len(result) == 3 * len(plain)
  assert "cube_found_front" not in slot_eval.evaluate(oracle, None, views, frames=4, views=("front",))


def _ari_by_pair_counting(a, b):
  """ARI from the four pair counts over all item pairs (an independent formula: Hubert and Arabie's)."""
  a, b = np.ravel(a), np.ravel(b)
  i, j = np.triu_indices(a.size, k=1)
  same_a, same_b = a[i] == a[j], b[i] == b[j]
  n11 = np.sum(same_a & same_b)
  n10 = np.sum(same_a & ~same_b)
  n01 = np.sum(~same_a & same_b)
  n00 = np.sum(~same_a & ~same_b)
  return 2.0 * (n11 * n00 - n10 * n01) / ((n11 + n10) * (n10 + n00) + (n11 + n01) * (n01 + n00))


def test_ari_known_values_and_pair_counting_reference():
  assert decomposition.adjusted_rand_index([0, 0, 1, 1], [5, 5, 2, 2]) == pytest.approx(1.0)
  assert decomposition.adjusted_rand_index([0, 0, 1, 1], [0, 1, 0, 1]) == pytest.approx(-0.5)
  # By hand: table [[2, 1], [0, 2]]: index 2, rows 4, cols 4, expected 16/10, max 4 -> 0.4 / 2.4.
  assert decomposition.adjusted_rand_index([0, 0, 0, 1, 1], [0, 0, 1, 1, 1]) == pytest.approx(0.4 / 2.4)
  rng = np.random.default_rng(0)
  for n, ka, kb in [(30, 3, 4), (57, 2, 6), (80, 5, 5)]:
    a, b = rng.integers(0, ka, n), rng.integers(0, kb, n)
    b[: n // 2] = a[: n // 2]  # partly agreeing
    assert decomposition.adjusted_rand_index(a, b) == pytest.approx(_ari_by_pair_counting(a, b), abs=1e-12)


def test_fg_ari_ignores_background_and_permutes_slots():
  seg = np.array([[[0, 1, 3, 3], [0, 1, 4, 4]]], np.uint8)                   # [T=1, H=2, W=4]
  slot_of = np.array([[[2, 2, 0, 0], [1, 1, 1, 1]]])                         # background slots are irrelevant
  masks = np.moveaxis(np.eye(3)[slot_of], -1, 1)                             # [T, K, H, W] one-hot
  assert decomposition.fg_ari(seg, masks) == pytest.approx(1.0)
  assert decomposition.matched_miou(seg, masks) == pytest.approx((1.0 + 0.5) / 2)  # object 4 shares its slot
  # With the table as foreground the slot holding id 1 also holds id 0 pixels: ARI over 6 pixels drops.
  assert decomposition.fg_ari(seg, masks, background_ids=(0,)) == pytest.approx(
      _ari_by_pair_counting(seg[seg > 0], slot_of[seg > 0]))
  merged = np.moveaxis(np.eye(3)[np.zeros_like(slot_of)], -1, 1)             # one slot takes everything
  assert decomposition.fg_ari(seg, merged) == pytest.approx(0.0)


def test_the_best_slot_iou_of_an_object_is_per_frame_and_nan_where_it_is_out_of_view():
  seg = np.zeros((3, 2, 4), np.uint8)
  seg[0, 0, 2:] = 3                    # frame 0: the cube's 2 pixels, alone in slot 1
  seg[1, 0, 2:] = 3                    # frame 1: they share slot 1 with 2 table pixels
  slot_of = np.zeros((3, 2, 4), int)
  slot_of[0, 0, 2:] = 1
  slot_of[1, 0, 2:] = slot_of[1, 1, 2:] = 1
  masks = np.moveaxis(np.eye(2)[slot_of], -1, 1)                             # [T, K, H, W] one-hot
  iou = decomposition.best_slot_iou(seg, masks, 3)
  np.testing.assert_allclose(iou[:2], [1.0, 0.5])
  assert np.isnan(iou[2])                                                     # frame 2: no cube in view


def test_found_by_area_bins_each_frame_by_the_objects_share_of_it():
  seg = np.zeros((3, 4, 4), np.uint8)
  seg[0, :2, :2] = 3                   # frame 0: 4 of 16 pixels, alone in slot 1: IoU 1
  seg[1, 0, 0] = 3                     # frame 1: 1 pixel, in slot 1 with 3 table pixels: IoU 1/4
  slot_of = np.zeros((3, 4, 4), int)   # frame 2: no cube
  slot_of[:2, :2, :2] = 1
  masks = np.moveaxis(np.eye(2)[slot_of], -1, 1)
  rows = decomposition.found_by_area(seg, masks, 3, edges=(0.0, 0.05, 0.1, 0.25))
  assert [(r["lo"], r["hi"], r["frames"]) for r in rows] == [(0.0, 0.05, 0), (0.05, 0.1, 1), (0.1, 0.25, 1)]
  assert np.isnan(rows[0]["iou"]) and np.isnan(rows[0]["found"])              # an empty bin
  assert (rows[1]["iou"], rows[1]["found"]) == (0.25, 0.0)
  assert (rows[2]["iou"], rows[2]["found"]) == (1.0, 1.0)                       # the last bin includes its top


def test_the_cube_by_area_command_refuses_a_folder_without_a_run_in_one_line(tmp_path, capsys):
  assert slot_eval.main([str(tmp_path / "absent")]) == 2
  err = capsys.readouterr().err.splitlines()
  assert len(err) == 1 and err[0].startswith("roboshape: error: ") and "absent" in err[0]


def test_per_frame_fg_ari_forgives_slots_that_swap_objects_between_frames():
  """evaluate's fg_ari scores the video as one clustering, fg_ari_frames each frame alone: two objects that swap
  slots halfway are a perfect decomposition of every frame but not of the video."""
  episode = synthetic_episode(3, length=4)
  seg = episode["segmentation"]

  def oracle(params, video, first_segmentation):  # stands in for the model: masks are one-hot segments, objects 3 and 4 swap at t = 2
    slot_of = np.select([seg == 3, seg == 4], [1, 2], 0)
    slot_of[2:] = np.select([seg[2:] == 3, seg[2:] == 4], [2, 1], 0)
    masks = np.moveaxis(np.eye(3, dtype=np.float32)[slot_of], -1, 1)[None]
    return {"masks": masks, "recon": video.astype(np.float32) / 255.0, "rgb": None}

  result = slot_eval.evaluate(oracle, None, [episode], frames=6)
  assert result["fg_ari_frames"] == pytest.approx(1.0)
  assert result["fg_ari"] < 0.1 and result["recon_mse"] == pytest.approx(0.0)


# ----------------------------------------------------------------------------------------------------------------
# pretrain.train_seeds: one run per seed, the best final validation FG-ARI served.

SEEDS = (3, 1)
FAKE_FG_ARI = {3: 0.5, 1: 0.2}     # the evaluator's FG-ARI, replaced so that the ranking is known: seed 3 wins


def fake_validation(scores):
  """make_validation: SAVi's real validation (figures, mIoU, ...) with FG-ARI set to scores[seed of the run]."""
  def make(config, root, model, episodes):
    real = slot_eval.validation(config, root, model, episodes)
    return pretrain.Validation(run=lambda params, step: dict(real.run(params, step), fg_ari=scores[config.seed]),
                               keys=real.keys, describe=real.describe, ylim=real.ylim)
  return make


def run_seeds(config, workdir, episodes, scores=FAKE_FG_ARI, fail_at=None):
  """The pretrain stage's training of `config`'s seeds on the one clip; returns (result, {seed: its Source})."""
  sources = {}

  def source(seed_config):
    sources[seed_config.seed] = Source(episodes[0]["image"], fail_at=fail_at)
    return sources[seed_config.seed], episodes

  return pretrain.train_and_select(config, workdir, source, fake_validation(scores)), sources


@pytest.fixture(scope="module")
def seeded(tmp_path_factory, trained):
  """SAVi trained with pretrain.train_seeds = SEEDS in a workdir of its own."""
  config = tiny_config()
  config.pretrain.train_seeds = SEEDS
  workdir = str(tmp_path_factory.mktemp("savi_seeds"))
  rundir.save_config(config, workdir)
  result, sources = run_seeds(config, workdir, trained["episodes"])
  return {"config": config, "workdir": workdir, "result": result, "sources": sources}


def test_no_seeds_keeps_the_single_run_layout(trained, encoder):
  root = rundir.pretrain_dir(trained["workdir"], "savi")
  assert sorted(os.listdir(root)) == ["checkpoints", "figures", "tb", "val_metrics.json", "val_metrics.png"]
  assert trained["result"]["step"] == STEPS and "runs" not in trained["result"]
  assert encoder.identity == f"savi:{os.path.abspath(rundir.checkpoints(root))}@{STEPS}"


def test_a_run_with_pretrain_from_workdir_serves_that_runs_savi_and_refuses_one_pretrained_otherwise(
    trained, encoder, tmp_path):
  """A grid's savi+proprio column: the SAVi its plain column's run pretrained, on the same dataset folder."""
  config = tiny_config()
  config.policy.proprio = True
  config.pretrain.from_workdir = trained["workdir"]
  config.data.dir = os.path.join(trained["workdir"], "data")    # the folder the plain run's data.dir="" names
  config.stages = tuple(s for s in config.stages if s != "pretrain")
  stages.check(config)
  workdir = str(tmp_path / "push_savi+proprio")
  rundir.save_config(config, workdir)
  served = savi_encoder.load_encoder(workdir)
  assert served.identity == encoder.identity and _tree_equal(served.params, encoder.params)
  assert encoders.build_encoder(config, workdir).identity.startswith(encoder.identity + "+proprio:")
  assert not os.path.exists(rundir.pretrain_dir(workdir, "savi"))
  # pretrained with another schedule, or on another dataset folder: refused in one line
  config.pretrain.train.steps = STEPS + 1
  rundir.save_config(config, workdir)
  with pytest.raises(UserError, match=r"was pretrained with other settings \(pretrain differ"):
    savi_encoder.load_encoder(workdir)
  config.pretrain.train.steps, config.data.dir = STEPS, ""
  rundir.save_config(config, workdir)
  with pytest.raises(UserError, match=r"other settings \(data differ"):
    savi_encoder.load_encoder(workdir)
  config.pretrain.from_workdir = str(tmp_path / "nowhere")
  rundir.save_config(config, workdir)
  with pytest.raises(UserError, match="holds no run yet .* run that run's pretrain stage first"):
    savi_encoder.load_encoder(workdir)
  # and a run cannot both serve another run's SAVi and pretrain one
  config.stages = ("pretrain",)
  with pytest.raises(UserError, match="drop 'pretrain' from --config.stages"):
    stages.check(config)


def test_each_seed_trains_in_its_own_folder_with_its_own_params(seeded):
  root = rundir.pretrain_dir(seeded["workdir"], "savi")
  assert sorted(os.listdir(root)) == ["seed_1", "seed_3", "seeds_fg_ari.png", "selected.json"]
  runs = seeded["result"]["runs"]
  assert list(runs) == list(SEEDS)
  for seed in SEEDS:
    folder = rundir.seed_dir(root, seed)
    assert os.path.isfile(os.path.join(folder, "figures", f"step_{STEPS:07d}.png"))
    assert os.path.isfile(os.path.join(folder, "val_metrics.png"))
    (entry,) = history_lib.load(folder, "val_metrics")
    assert entry["step"] == STEPS and entry["fg_ari"] == FAKE_FG_ARI[seed] and 0 <= entry["miou"] <= 1
    with Checkpointer(rundir.checkpoints(folder)) as ckpt:
      assert ckpt.latest_step() == STEPS
    assert runs[seed]["step"] == STEPS and seeded["sources"][seed].served == list(range(STEPS))
  assert not _tree_equal(runs[3]["params"], runs[1]["params"])          # another init for another seed
  assert os.path.getsize(rundir.seeds_figure(root, "fg_ari")) > 1000


def test_the_seed_with_the_best_final_fg_ari_is_selected(seeded):
  assert seeded["result"]["selected"] == 3
  with open(rundir.selection_path(rundir.pretrain_dir(seeded["workdir"], "savi"))) as f:
    selection = json.load(f)
  assert selection["selected_seed"] == 3 and selection["metric"] == "fg_ari" and selection["higher_is_better"]
  assert [(r["seed"], r["step"], r["fg_ari"]) for r in selection["seeds"]] == [(3, STEPS, 0.5), (1, STEPS, 0.2)]
  assert all(0 <= r["miou"] <= 1 for r in selection["seeds"])


def test_a_finished_seed_stage_retrains_nothing(seeded):
  result, sources = run_seeds(seeded["config"], seeded["workdir"], [synthetic_episode(1), synthetic_episode(2)],
                              fail_at=0)
  assert all(not s.served for s in sources.values()) and sorted(sources) == sorted(SEEDS)
  assert result["selected"] == 3 and result["selection"] == seeded["result"]["selection"]
  for seed in SEEDS:
    assert _tree_equal(result["runs"][seed]["params"], seeded["result"]["runs"][seed]["params"])


def test_the_encoder_served_is_the_selected_seeds_and_follows_the_selection(seeded, tmp_path):
  encoder = savi_encoder.load_encoder(seeded["workdir"])
  assert _tree_equal(encoder.params, seeded["result"]["runs"][3]["params"])
  assert f"{os.sep}savi{os.sep}seed_3{os.sep}checkpoints@{STEPS}" in encoder.identity
  _, params, step = savi_encoder.load(seeded["workdir"])
  assert step == STEPS and _tree_equal(params, encoder.params)
  # Seed 1's final FG-ARI rises above seed 3's; the stage, run again, trains nothing and selects seed 1 instead.
  workdir = str(tmp_path / "run")
  shutil.copytree(seeded["workdir"], workdir)
  before = savi_encoder.load_encoder(workdir).identity
  folder = rundir.seed_dir(rundir.pretrain_dir(workdir, "savi"), 1)
  history = history_lib.load(folder, "val_metrics")
  history[-1]["fg_ari"] = 0.9
  with open(os.path.join(folder, "val_metrics.json"), "w") as f:
    json.dump(history, f)
  result, sources = run_seeds(seeded["config"], workdir, [synthetic_episode(1)], fail_at=0)
  assert result["selected"] == 1 and not any(s.served for s in sources.values())
  after = savi_encoder.load_encoder(workdir)
  assert after.identity != before and f"{os.sep}seed_1{os.sep}" in after.identity
  assert _tree_equal(after.params, seeded["result"]["runs"][1]["params"])


def test_a_missing_or_stale_selection_is_refused_with_one_line(seeded, tmp_path):
  workdir = str(tmp_path / "run")
  shutil.copytree(seeded["workdir"], workdir)
  config = tiny_config()
  config.pretrain.train_seeds = (3, 1, 5)            # a seed more than the selection was made among
  rundir.save_config(config, workdir)
  with pytest.raises(UserError, match=r"selected among seeds \(1, 3\).*run the pretrain stage again"):
    savi_encoder.load_encoder(workdir)
  os.remove(rundir.selection_path(rundir.pretrain_dir(workdir, "savi")))
  with pytest.raises(UserError, match="no SAVi seed is selected yet"):
    savi_encoder.load_encoder(workdir)


def test_a_final_validation_lost_to_a_kill_is_redone_on_resume(seeded, tmp_path):
  """Killed after its last checkpoint and before its last validation: the resumed stage validates that step
  (without training) before it selects."""
  workdir = str(tmp_path / "run")
  shutil.copytree(seeded["workdir"], workdir)
  folder = rundir.seed_dir(rundir.pretrain_dir(workdir, "savi"), 1)
  with open(os.path.join(folder, "val_metrics.json"), "w") as f:
    json.dump([], f)
  result, sources = run_seeds(seeded["config"], workdir, [synthetic_episode(1), synthetic_episode(2)], fail_at=0)
  assert not any(s.served for s in sources.values())
  assert [(h["step"], h["fg_ari"]) for h in history_lib.load(folder, "val_metrics")] == [(STEPS, 0.2)]
  assert result["selected"] == 3


def test_selection_takes_the_last_evaluation_ties_to_the_lower_seed_and_nan_last(tmp_path):
  root = str(tmp_path)
  config = tiny_config()
  finals = {4: [(10, 0.9), (20, 0.4)], 2: [(10, 0.1), (20, 0.4)], 0: [(10, 0.3), (20, float("nan"))]}
  for seed, entries in finals.items():
    for step, ari in entries:
      history_lib.record(rundir.seed_dir(root, seed), "val_metrics", step, {"fg_ari": ari, "recon_mse": ari}, step,
                         keys=("fg_ari",))
  steps = {seed: 20 for seed in finals}
  fg_ari = encoders.get("savi").model.selection
  chosen = pretrain.select_seed(config, root, steps, fg_ari, "SAVi")
  assert chosen["selected_seed"] == 2                      # 4's 0.9 was not its last; 2 and 4 tie at 0.4; NaN last
  assert rundir.load_selection(root) == chosen
  lower = pretrain.select_seed(config, root, steps, encoders.Selection("recon_mse", False, "MSE"), "AE")
  assert lower["selected_seed"] == 2                       # lower is better: 2 and 4 tie at 0.4, NaN still last
  with pytest.raises(UserError, match="seed 4 has no validation FG-ARI at its last step 30"):
    pretrain.select_seed(config, root, {**steps, 4: 30}, fg_ari, "SAVi")


# ------------------------------------------------------------------------------------------------- conditional SAVi
def test_first_frame_cues_are_each_ids_box_and_nothing_for_an_absent_id():
  """Row k of the cues is id k's box in pixel centres of [-1, 1] (top, left, bottom, right) after a 1; an id absent
  from the frame, or beyond the slots, gives no cue."""
  seg = np.zeros((1, 16, 16), np.uint8)
  seg[0, 2:7, 4:9] = 3                                    # rows 2..6, columns 4..8
  seg[0, 15, 15] = 7                                      # an id with no slot (K = 5)
  cues = np.asarray(savi.first_frame_cues(seg, 5))
  centre = lambda i: (2 * i + 1) / 16 - 1
  np.testing.assert_allclose(cues[0, 3], [1, centre(2), centre(4), centre(6), centre(8)])
  np.testing.assert_allclose(cues[0, 0], [1, centre(0), centre(0), centre(15), centre(15)])    # the backdrop
  assert not cues[0, [1, 2, 4]].any()
  assert savi.CUE_FIELDS == ("present", "top", "left", "bottom", "right")


@pytest.fixture(scope="module")
def conditional(tmp_path_factory):
  """A tiny conditional SAVi (savi.init_mean "cues", a slot for each of the ids 0..4), trained a few steps on
  clips with their segmentation, validated once."""
  config = tiny_config()
  config.savi.num_slots, config.savi.init_mean = 5, "cues"
  config.env.min_distractors = config.env.max_distractors = 0    # ids 0..4: backdrop, table, robot, two squares
  p = config.pretrain
  p.train.steps, p.train.checkpoint_every, p.eval.every, p.eval.episodes = 4, 4, 4, 1
  workdir = str(tmp_path_factory.mktemp("conditional_savi"))
  rundir.save_config(config, workdir)
  episodes = [synthetic_episode(3), synthetic_episode(4)]

  def batches_from(start):
    for i in itertools.count(start):
      e = episodes[i % 2]
      yield {"video": e["image"][None], "segmentation": e["segmentation"][None], "episode_seed": np.array([i])}

  result = pretrain.train_and_select(config, workdir, lambda c: (batches_from, episodes[:1]), slot_eval.validation)
  return {"config": config, "workdir": workdir, "result": result, "episodes": episodes}


def test_a_conditional_savi_starts_each_episode_from_its_first_frames_cues(conditional):
  """The frozen conditional SAVi reads the segmentation: its tokens are the model's slots from the first frame's
  cues (as validation decomposes), they change with the first frame's boxes and not with a later frame's
  segmentation, and each episode of a batch starts from its own cues."""
  model, params, step = savi_encoder.load(conditional["workdir"])
  assert savi.conditional(model) and step == 4
  figures = os.path.join(rundir.pretrain_dir(conditional["workdir"], "savi"), rundir.FIGURES_DIR)
  assert os.listdir(figures)                                # validated, from the validation episode's first cues
  enc = savi_encoder.load_encoder(conditional["workdir"])
  assert enc.inputs == ("image", "segmentation")
  episode = conditional["episodes"][1]
  obs = {"image": episode["image"], "segmentation": episode["segmentation"]}
  tokens = np.asarray(enc.encode_episode(obs))
  out = savi.decompose(model, params, episode["image"][None], episode["segmentation"][None, 0])
  np.testing.assert_allclose(tokens, np.asarray(out["slots"][0]), atol=1e-5)
  later = dict(obs, segmentation=np.concatenate([obs["segmentation"][:1], np.zeros_like(obs["segmentation"][1:])]))
  np.testing.assert_allclose(np.asarray(enc.encode_episode(later)), tokens, atol=1e-6)
  moved = dict(obs, segmentation=np.roll(obs["segmentation"], 4, axis=2))
  assert np.abs(np.asarray(enc.encode_episode(moved)) - tokens).max() > 1e-3
  batch = jax.tree.map(lambda *x: np.stack(x), conditional["episodes"][0], episode)
  both = np.asarray(enc.encode_batch({"image": batch["image"], "segmentation": batch["segmentation"]}))
  np.testing.assert_allclose(both[1], tokens, atol=1e-5)
  with pytest.raises(UserError, match="first segmentation"):
    videos.SaviSlotVideo(conditional["workdir"])(episode["image"])


def test_the_cond_column_is_savi_with_cues_and_needs_a_slot_per_object():
  """savi+cond sets savi.init_mean='cues' and reads back as that column; another encoder cannot take it; a
  conditional SAVi with fewer slots than the ids its scenes show is refused in one line."""
  from roboshape.encoders import columns  # pylint: disable=import-outside-toplevel
  config = common.get_config("pick", "savi+cond", "small")
  assert config.savi.init_mean == "cues" and columns.of_config(config) == "savi+cond"
  assert not columns.policy_only("savi+cond")
  with pytest.raises(UserError, match="applies to savi only"):
    columns.parse("ae+cond")
  config.savi.num_slots = 8
  with pytest.raises(UserError, match=r"savi.num_slots=8 .* use at least 9 slots"):
    stages.check(config)
