"""The encoder registry and the `state` encoder: names, inputs, the privileged-state token and its layout."""
import numpy as np
import pytest

from configs import common
from roboshape import encoders
from roboshape import stages
from roboshape.encoders import columns
from roboshape.errors import UserError
from roboshape.encoders import state as state_encoder
from roboshape.envs import state as state_lib


def test_the_registry_lists_every_encoder_with_its_needs():
  assert {"savi", "r3m", "dino", "state"} <= set(encoders.names())
  assert encoders.get("savi").pretrain and not encoders.get("state").pretrain
  assert encoders.get("state").inputs == ("state",) and encoders.get("r3m").inputs == ("image",)
  with pytest.raises(UserError, match="unknown encoder 'nope'; registered encoders: .*savi"):
    encoders.get("nope")
  # A config of an encoder without pretraining has no pretrain stage.
  assert "pretrain" not in common.get_config("push", "state", "tiny").stages


def test_a_registered_toy_encoder_is_a_config_choice():
  kind = encoders.register(encoders.Kind(name="toy_registered", inputs=("segmentation",), pretrain="",
                                         build=lambda config, workdir: None, title="Toy", description="test"))
  try:
    config = common.get_config("pick", "toy_registered", "tiny")
    assert config.encoder == "toy_registered" and "pretrain" not in config.stages
  finally:
    encoders.unregister(kind.name)
  with pytest.raises(ValueError, match="inputs"):
    encoders.Kind(name="bad", inputs=("pixels",), pretrain="", build=None, title="", description="")


def test_the_state_vector_packs_fields_in_their_documented_places():
  n, k = 2, 3
  rng = np.random.default_rng(0)
  fields = dict(tcp_pos=rng.normal(size=(n, 3)), tcp_quat=rng.normal(size=(n, 4)), gripper=rng.normal(size=(n,)),
                arm_qpos=rng.normal(size=(n, 7)), cube_pos=rng.normal(size=(n, 3)), cube_quat=rng.normal(size=(n, 4)),
                goal_pos=rng.normal(size=(n, 3)))
  rows = rng.normal(size=(n, k, 4))
  present = np.array([[True, True, False], [True, False, False]])
  vec = state_lib.pack(**fields, distractors=rows, present=present)
  assert vec.shape == (n, state_lib.DIM) == (2, 65) and vec.dtype == np.float32
  cuts = state_lib.slices()
  for name, value in fields.items():
    np.testing.assert_allclose(vec[:, cuts[name]], np.reshape(value, (n, -1)), rtol=1e-6)
  dist = vec[:, cuts["distractors"]].reshape(n, state_lib.MAX_DISTRACTORS, 5)
  np.testing.assert_allclose(dist[0, :2, :4], rows[0, :2], rtol=1e-6)
  assert dist[..., 4].tolist() == [[1, 1, 0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0, 0, 0]]
  assert not dist[0, 2:].any() and not dist[1, 1:].any()      # padding rows are all zero
  assert "[7:8] gripper" in state_lib.describe()


def test_the_state_token_is_the_vector_in_decimetres_then_relative_positions():
  enc = encoders.get("state").build(common.get_config("push", "state", "tiny"), "")
  assert (enc.inputs, enc.num_tokens, enc.token_dim) == (("state",), 1, state_lib.DIM + 9)
  states = np.random.default_rng(1).normal(size=(2, 5, state_lib.DIM)).astype(np.float32)
  tokens = np.asarray(enc.encode_batch({"state": states, "image": np.zeros((2, 5, 4, 4, 3), np.uint8)}))
  assert tokens.shape == (2, 5, 1, state_lib.DIM + 9)
  cuts = state_lib.slices()
  np.testing.assert_allclose(tokens[:, :, 0, cuts["cube_pos"]], 10 * states[..., cuts["cube_pos"]], rtol=1e-6)
  np.testing.assert_allclose(tokens[:, :, 0, cuts["cube_quat"]], states[..., cuts["cube_quat"]], rtol=1e-6)
  # The cube, the goal (from the tcp) and the goal from the cube, in units of 0.1 m.
  cube, tcp, goal = (states[..., cuts[k]] for k in ("cube_pos", "tcp_pos", "goal_pos"))
  relative = tokens[:, :, 0, state_lib.DIM:]
  np.testing.assert_allclose(relative, np.concatenate([cube - tcp, goal - tcp, goal - cube], -1) * 10, rtol=1e-5,
                             atol=1e-5)
  scale = state_encoder.token_scale()[cuts["distractors"]].reshape(-1, 5)
  assert (scale[:, :4] == 10).all() and (scale[:, 4] == 1).all()
  with pytest.raises(KeyError, match="lacks state"):
    enc.encode_batch({"image": np.zeros((1, 2, 4, 4, 3), np.uint8)})


def _state_tokens_before_and_after(config):
  """The state tokens [2, 3, TOKEN_DIM] of random states, from the state encoder of the default state section and
  from that of `config` (checked), whose identity differs and whose width does not."""
  stages.check(config)
  full = encoders.get("state").build(common.get_config(config.task, "state", "tiny"), "")
  changed = encoders.get("state").build(config, "")
  assert changed.identity != full.identity and changed.token_dim == full.token_dim
  states = np.random.default_rng(2).normal(size=(2, 3, state_lib.DIM)).astype(np.float32)
  return (np.asarray(full.encode_batch({"state": states}))[:, :, 0],
          np.asarray(changed.encode_batch({"state": states}))[:, :, 0])


def test_withholding_a_state_field_zeroes_its_entries_and_the_relative_ones_made_from_it_and_nothing_else():
  config = common.get_config("pick", "state", "tiny")
  config.state.withhold = ("cube_quat", "cube_pos")
  a, b = _state_tokens_before_and_after(config)
  cuts = state_lib.slices()
  gone = np.zeros(a.shape[-1], bool)
  gone[cuts["cube_quat"]] = gone[cuts["cube_pos"]] = True
  gone[state_lib.DIM:state_lib.DIM + 3] = True          # cube - tcp
  gone[state_lib.DIM + 6:] = True                        # goal - cube; goal - tcp (entries 3:6) stays
  assert (b[..., gone] == 0).all() and (a[..., gone] != 0).all()
  np.testing.assert_array_equal(b[..., ~gone], a[..., ~gone])
  for bad in (("cube_yaw",), ("gripper", "gripper")):
    config.state.withhold = bad
    with pytest.raises(UserError, match=r"^state.withhold=.*: use a tuple of distinct state fields among tcp_pos, "):
      stages.check(config)


def test_a_dataset_without_state_is_a_one_line_error_for_the_state_encoder(tmp_path):
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  enc = encoders.get("state").build(None, "")
  old = dict(image=np.zeros((3, 4, 4, 3), np.uint8), segmentation=np.zeros((3, 4, 4), np.uint8),
             action=np.zeros((2, 7), np.float32), seed=0, success=True)
  with pytest.raises(UserError, match="needs observation/state, which this dataset does not store: collect it again"
                     ) as e:
    cache.encode_split(enc, iter([old]), str(tmp_path / "features"))
  assert "\n" not in str(e.value)


def test_the_proprio_option_appends_the_hand_pose_token_and_changes_nothing_else():
  from roboshape.encoders import objects as objects_encoder  # pylint: disable=import-outside-toplevel
  from roboshape.encoders import proprio  # pylint: disable=import-outside-toplevel
  config = common.get_config("push", "objects", "tiny")
  assert config.policy.proprio is False
  plain = encoders.build_encoder(config, "")
  config.policy.proprio = True
  enc = encoders.build_encoder(config, "")
  assert enc.inputs == plain.inputs + ("state",)
  assert (enc.num_tokens, enc.token_dim) == (plain.num_tokens + 1, objects_encoder.DIM + 1)
  assert enc.identity.startswith(plain.identity + "+proprio:") and enc.identity != plain.identity
  rng = np.random.default_rng(2)
  b, t, h = 2, 3, 8
  obs = {"image": rng.integers(0, 255, (b, t, h, h, 3), dtype=np.uint8),
         "segmentation": rng.integers(0, 5, (b, t, h, h), dtype=np.uint8),
         "state": rng.normal(size=(b, t, state_lib.DIM)).astype(np.float32)}
  base = np.asarray(plain.encode_batch(obs))
  tokens = np.asarray(enc.encode_batch(obs))
  assert tokens.shape == (b, t, plain.num_tokens + 1, objects_encoder.DIM + 1)
  # The encoder's own tokens are unchanged, flag 0; an absent object's token stays all zero (the trunk masks it).
  np.testing.assert_array_equal(tokens[:, :, :-1, :-1], base)
  assert not tokens[:, :, :-1, -1].any()
  assert ((tokens[:, :, :-1] == 0).all(-1) == (base == 0).all(-1)).all()
  # The last token: the state's tcp position (dm), tcp orientation and finger opening (dm) at the same step, flag 1.
  cuts = state_lib.slices()
  s = obs["state"]
  expected = np.concatenate([10 * s[..., cuts["tcp_pos"]], s[..., cuts["tcp_quat"]], 10 * s[..., cuts["gripper"]]],
                            -1)
  own = tokens[:, :, -1]
  np.testing.assert_allclose(own[..., :proprio.SIZE], expected, rtol=1e-6)
  np.testing.assert_allclose(proprio.token(s), expected, rtol=1e-6)
  assert not own[..., proprio.SIZE:-1].any() and (own[..., -1] == 1).all()


def test_the_proprio_token_pads_to_a_wider_encoders_width():
  from roboshape.encoders import proprio  # pylint: disable=import-outside-toplevel
  config = common.get_config("push", "state", "tiny")
  config.policy.proprio = True
  enc = encoders.build_encoder(config, "")
  # The state token (74 wide) is wider than the 8 proprioception entries: they are padded to its width.
  assert (enc.num_tokens, enc.token_dim, enc.inputs) == (2, state_lib.DIM + 9 + 1, ("state",))
  states = np.random.default_rng(3).normal(size=(1, 2, state_lib.DIM)).astype(np.float32)
  tokens = np.asarray(enc.encode_batch({"state": states}))
  np.testing.assert_allclose(tokens[0, :, 1, :proprio.SIZE], proprio.token(states[0]), rtol=1e-6)
  assert not tokens[0, :, 1, proprio.SIZE:-1].any() and tokens[0, :, 0, -1].tolist() == [0, 0]


# ----------------------------------------------------------------------------------------------------------------
# A new encoder is one module: tests/toy_encoder.py, through the config check, the stage wiring and the pipeline.


@pytest.fixture()
def toy():
  """tests/toy_encoder.py, registered for the test (as importing it registers it), and out of the registry after."""
  import toy_encoder  # pylint: disable=import-outside-toplevel
  encoders.register(toy_encoder.KIND)
  yield toy_encoder
  encoders.unregister(toy_encoder.NAME)


def _toy_config(toy, data_dir=""):
  """push x toy at :tiny on the 16x16 synthetic dataset: a 1-layer policy trained 4 steps on 2 frames of history,
  evaluated on one 4-step rollout at the train level."""
  config = common.get_config("push", toy.NAME, "tiny")
  config.toy = toy.section()
  config.env.resolution, config.env.max_episode_steps = 16, 4
  config.data.dir = data_dir
  config.sim.num_workers = 1
  p = config.policy
  p.history, p.width, p.num_layers, p.num_heads, p.dropout = 2, 16, 1, 2, 0.0
  p.train.update(dict(steps=4, batch_size=4, warmup_steps=1, log_every=2, eval_every=2, checkpoint_every=2,
                      val_batch_size=4))
  config.eval.levels, config.eval.num_seeds, config.eval.rollouts_per_seed = ("train",), 1, 1
  return config


def test_a_new_encoders_module_is_all_the_config_check_and_stage_wiring_need(toy):
  # pylint: disable=import-outside-toplevel
  from configs import reproduce
  from roboshape import stages
  config = _toy_config(toy)
  assert config.encoder == "toy" and "pretrain" not in config.stages           # no pretrain stage of its own
  stages.check(config)
  config.toy.scale = 0.0                                                         # its own range, from its module
  with pytest.raises(UserError, match=r"^toy\.scale=0\.0: use a number > 0 \(the factor"):
    stages.check(config)
  config.toy.scale = 1.0
  config.stages = ("cache", "pretrain")
  with pytest.raises(UserError, match="the toy encoder has no pretrain stage; drop it from --config.stages"):
    stages.check(config)
  config.stages = ("cache", "train_policy", "evaluate")
  assert all(callable(stages.stage_runner(name, config)) for name in config.stages)
  other = common.get_config("push", "r3m", "tiny")                               # the toy's section is its own:
  other.toy = toy.section()                                                      # another encoder's run never
  other.toy.scale = -1.0                                                         # checks it
  stages.check(other)
  grid = reproduce.get_config("tiny")
  grid.grid.encoders = ("toy", "savi")
  grid.toy = toy.section()
  stages.check(grid)
  runs = [(encoder, tuple(sub.stages)) for _, encoder, sub, _ in stages.grid_configs(grid, "/w")]
  assert runs == [("savi", tuple(common.STAGES[:-1])), ("toy", tuple(s for s in common.STAGES[:-1]
                                                                     if s != "pretrain"))]


def test_a_new_encoders_module_places_it_in_the_tables_the_verdict_and_the_gpu_projection(toy, monkeypatch):
  # pylint: disable=import-outside-toplevel
  import importlib
  import os
  from roboshape.report import claims
  from roboshape.report import tables
  assert tables.sort_encoders(("toy", "state", "savi", "dino", "toy+proprio")) == (
      "dino", "savi", "state", "toy", "toy+proprio")                               # its Kind's order: after them
  assert claims.global_encoders()[-1] == "toy" and claims.compared(("savi", "toy", "objects")) == ["toy", "objects"]
  assert claims.object_centric() == "savi" and claims.privileged() == "state"
  monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))   # whatever its import sets is undone after
  monkeypatch.syspath_prepend(os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
  gpu_scaleup = importlib.import_module("gpu_scaleup")
  assert gpu_scaleup.tokens_per_frame(_toy_config(toy), "toy") == "4 x 3"
  assert gpu_scaleup.tokens_per_frame(common.get_config("push", "objects", "small"), "objects") == "10 x 12"
  with pytest.raises(ValueError, match="family 'global-ish' must be one of"):
    encoders.Kind(name="bad", inputs=("image",), pretrain="", build=None, title="", description="",
                  family="global-ish")


@pytest.mark.usefixtures("cheap_xla")
def test_a_new_encoder_runs_the_tiny_pipeline(toy, synthetic_dataset, tmp_path):
  """cache -> train_policy -> evaluate (the real simulator, one short rollout) -> report, on the shared synthetic
  dataset: its features are the toy's tokens, its table names it by its title, and it gets no slot videos."""
  import csv  # pylint: disable=import-outside-toplevel
  import json  # pylint: disable=import-outside-toplevel
  import os  # pylint: disable=import-outside-toplevel
  pytest.importorskip("roboshape.sim")
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  from roboshape.data import reader  # pylint: disable=import-outside-toplevel
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  config = _toy_config(toy, os.path.dirname(os.path.dirname(synthetic_dataset)))  # <dir>/roboshape_push/1.0.0
  config.stages = ("cache", "train_policy", "evaluate", "report")
  workdir = str(tmp_path / "push_toy")
  stages.run(config, workdir)
  encoder = encoders.build_encoder(config, workdir)
  features = cache.feature_dir(config, workdir, encoder)
  with open(os.path.join(features, "manifest.json")) as f:
    manifest = json.load(f)
  assert (manifest["encoder"], manifest["num_tokens"], manifest["token_dim"]) == ("toy", 4, 3)
  episode = next(reader.read_episodes(synthetic_dataset, "val"))
  first = episode["image"][0].astype(np.float32) / 255.0                       # [16, 16, 3]
  np.testing.assert_allclose(cache.load_split(features, "val")["features"][0, 1], first[:8, 8:].mean(axis=(0, 1)),
                             atol=1e-6)                                          # token 1: the top right quadrant
  with open(os.path.join(workdir, "eval", "results.csv")) as f:
    rows = list(csv.DictReader(f))
  assert [(r["encoder"], r["level"]) for r in rows] == [("toy", "train")] and 1 <= int(rows[0]["length"]) <= 4
  assert "| | Toy |" in open(os.path.join(workdir, "eval", "table.md")).read()
  videos = os.listdir(os.path.join(workdir, "eval", "videos"))
  assert any(v.endswith(".mp4") for v in videos) and not any("_slots" in v for v in videos)
  assert os.path.isfile(os.path.join(workdir, "report", "report.md"))


def test_the_absolute_state_token_zeroes_the_relative_entries_alone():
  config = common.get_config("pick", "state", "tiny")
  config.state.relative = False
  a, b = _state_tokens_before_and_after(config)
  np.testing.assert_array_equal(b[..., :state_lib.DIM], a[..., :state_lib.DIM])
  assert (b[..., state_lib.DIM:] == 0).all() and (a[..., state_lib.DIM:] != 0).all()


def test_pose_tokens_are_the_objects_exact_positions_in_decimetres_and_absent_distractors_are_zero():
  from roboshape.encoders import poses  # pylint: disable=import-outside-toplevel
  from roboshape.envs import palettes  # pylint: disable=import-outside-toplevel
  config = common.get_config("pick", "poses", "tiny")
  enc = encoders.build_encoder(config, "")
  k = int(config.env.max_distractors)
  assert (enc.num_tokens, enc.token_dim, enc.inputs) == (3 + k, poses.DIM, ("state",))
  cuts = state_lib.slices()
  tcp, cube, goal = (0.1, -0.2, 0.3), (0.05, 0.0, 0.02), (-0.1, 0.1, 0.0)
  state = np.zeros((1, 1, state_lib.DIM), np.float32)
  state[..., cuts["tcp_pos"]], state[..., cuts["cube_pos"]], state[..., cuts["goal_pos"]] = tcp, cube, goal
  state[..., cuts["gripper"]] = 0.08
  rows = np.zeros((state_lib.MAX_DISTRACTORS, 5), np.float32)
  rows[0] = (0.2, 0.2, 0.03, 0.025, 1.0)                   # one distractor present, the rest padding
  state[..., cuts["distractors"]] = rows.reshape(-1)
  tokens = np.asarray(enc.encode_batch({"state": state}))[0, 0]
  colour = lambda rgb: np.asarray(rgb, np.float32) / 255
  np.testing.assert_allclose(tokens[0], np.r_[1, 10 * np.array(tcp), 0, 0.8, colour(poses.HAND_COLOUR)], rtol=1e-6)
  np.testing.assert_allclose(tokens[1], np.r_[1, 10 * np.array(cube), 0.2, 0, colour(palettes.CUBE_COLOR)],
                             rtol=1e-6)
  np.testing.assert_allclose(tokens[2], np.r_[1, 10 * np.array(goal), 0, 0, colour(palettes.GOAL_COLOR)], rtol=1e-6)
  np.testing.assert_allclose(tokens[3], np.r_[1, 2, 2, 0.3, 0.25, 0, colour(poses.DISTRACTOR_COLOUR)], rtol=1e-6)
  assert not tokens[4:].any()                               # padding: all zero, masked out by the trunk


def test_hand_relative_tokens_carry_each_objects_position_from_the_hand_and_need_proprio_and_positions():
  from roboshape.encoders import poses  # pylint: disable=import-outside-toplevel
  from roboshape.encoders import proprio  # pylint: disable=import-outside-toplevel
  config = common.get_config("pick", "poses", "tiny")
  columns.apply(config, "poses+proprio+rel")
  stages.check(config)
  assert columns.of_config(config) == "poses+proprio+rel"
  plain = encoders.get("poses").build(config, "")
  enc = encoders.build_encoder(config, "")
  assert (enc.num_tokens, enc.token_dim) == (plain.num_tokens + 1, max(poses.DIM + 3, proprio.SIZE) + 1)
  assert "+relative:" in enc.identity
  cuts = state_lib.slices()
  state = np.zeros((1, 1, state_lib.DIM), np.float32)
  state[..., cuts["tcp_pos"]], state[..., cuts["cube_pos"]] = (0.1, 0.0, 0.2), (0.05, 0.1, 0.02)
  tokens = np.asarray(enc.encode_batch({"state": state}))[0, 0]
  base = np.asarray(plain.encode_batch({"state": state}))[0, 0]
  np.testing.assert_allclose(tokens[:plain.num_tokens, :poses.DIM], base)
  relative = tokens[:plain.num_tokens, poses.DIM:poses.DIM + 3]
  np.testing.assert_allclose(relative[0], 0, atol=1e-6)                          # the hand from the hand
  np.testing.assert_allclose(relative[1], [-0.5, 1.0, -1.8], rtol=1e-5)          # the cube, in units of 0.1 m
  assert not tokens[4:plain.num_tokens].any()                                     # absent distractors stay all zero
  config.policy.proprio = False
  with pytest.raises(UserError, match=r"^policy.hand_relative=True needs the tool centre point"):
    stages.check(config)
  savi = common.get_config("pick", "savi", "tiny")
  columns.apply(savi, "savi+proprio+rel")
  with pytest.raises(UserError, match="slots are placed in 3-D only with the camera's depth: set env.depth=True"):
    stages.check(savi)
  savi.env.depth = True
  stages.check(savi)
  objects = common.get_config("pick", "objects", "tiny")
  columns.apply(objects, "objects+proprio+rel")
  with pytest.raises(UserError, match="only with depth: set env.depth=True"):
    stages.check(objects)


def test_an_object_tokens_point_is_its_centroid_at_its_depth_through_the_camera():
  from roboshape.encoders import objects  # pylint: disable=import-outside-toplevel
  from roboshape.envs import camera  # pylint: disable=import-outside-toplevel
  world = np.array([[0.05, -0.1, 0.02], [0.0, 0.0, 0.3]], np.float32)
  row, col, depth = camera.project(world)
  tokens = np.zeros((2, objects.DIM), np.float32)
  cuts = objects.slices()
  tokens[:, 0], tokens[:, cuts["centroid"]], tokens[:, cuts["depth"]] = 1, np.stack([row, col], -1), depth[:, None]
  tokens[1, cuts["depth"]] = 0.0                                                  # no depth: no point
  where, valid = objects.points(tokens)
  np.testing.assert_allclose(np.asarray(where)[0], world[0], atol=1e-5)
  assert np.asarray(valid).tolist() == [True, False]


def test_every_encoders_trainer_and_evaluator_is_in_the_stages_tables():
  """Kind.pretrain and Kind.evaluator name entries of roboshape/stages.py's tables, each a function that runs or
  validates; the pretrain stage of each encoder that has one is its trainer given its evaluator's validation."""
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  for name in encoders.names():
    kind = encoders.get(name)
    assert not kind.pretrain or callable(stages.PRETRAINERS[kind.pretrain]), name
    assert not kind.evaluator or callable(stages.EVALUATORS[kind.evaluator]), name
  assert {encoders.get(n).evaluator for n in ("savi", "ae")} == set(stages.EVALUATORS)
  calls = []
  config = common.get_config("push", "savi", "tiny")
  original = stages.PRETRAINERS["loop"]
  try:
    stages.PRETRAINERS["loop"] = lambda *args: calls.append(args)
    stages.stage_runner("pretrain", config)("/w")
  finally:
    stages.PRETRAINERS["loop"] = original
  assert calls == [(config, "/w", stages.EVALUATORS["slots"])]
