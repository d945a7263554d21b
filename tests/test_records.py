"""Runs whose record is true: a diverging training stops at once (no non-finite checkpoint, the stage not done), a
workdir's config.json always describes what it holds (each stage's fingerprint.json; a rerun with other settings is
refused before anything is touched, --redo sets the old output aside and runs the stage again, more steps resume,
a workdir from before fingerprints is adopted once), non-finite features, actions and states are refused naming
the episode, and a policy that cannot act is blamed in one line.

Tiny shapes throughout: a pick x state run (no pretraining) on a synthetic dataset with states, its policy a
16-wide one-layer trunk trained 4 steps, compiled at XLA's cheap optimisation level."""
import json
import os
import shutil

import numpy as np
import pytest

from configs import common
from conftest import _synthetic_episode
from roboshape import data as data_lib
from roboshape import rundir
from roboshape import stages
from roboshape.data import collect
from roboshape.data import reader
from roboshape.data import rlds
from roboshape.errors import UserError


pytestmark = pytest.mark.usefixtures("cheap_xla_module")     # compile-bound: XLA's cheap optimisation level


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
  """A config.data.dir holding a complete pick dataset with states (16x16, 4 train + 1 val synthetic episodes)."""
  root = str(tmp_path_factory.mktemp("records_data"))
  rlds.write_dataset(os.path.join(root, "roboshape_pick", "1.0.0"),
                     {"train": [_synthetic_episode(s, task="pick", state=True) for s in range(4)],
                      "val": [_synthetic_episode(1_000_000, task="pick", state=True)]})
  return root


def _config(data_dir, **train):
  """configs/pick_state.py:tiny on `data_dir`, running train_policy alone, shrunk to a few steps."""
  config = common.get_config("pick", "state", "tiny")
  config.env.resolution, config.data.dir, config.stages = 16, data_dir, ("train_policy",)
  p = config.policy
  p.history, p.width, p.num_layers, p.num_heads, p.dropout = 2, 16, 1, 2, 0.0
  p.train.update(dict(steps=4, batch_size=4, warmup_steps=1, log_every=2, eval_every=2, checkpoint_every=2,
                      val_batch_size=4))
  p.train.update(train)
  return config


def _copy(workdir, tmp_path):
  out = str(tmp_path / "run")
  shutil.copytree(workdir, out)
  return out


def _snapshot(workdir):
  """{relative path: (size, mtime_ns)} of every file under `workdir`, and every folder."""
  out = {}
  for d, dirs, files in os.walk(workdir):
    for name in dirs + files:
      path = os.path.join(d, name)
      st = os.stat(path)
      out[os.path.relpath(path, workdir)] = (st.st_size if name in files else None, st.st_mtime_ns)
  return out


def _fields(folder):
  with open(rundir.fingerprint_path(folder)) as f:
    return json.load(f)["fields"]


def _checkpoints_finite(workdir):
  """{step: whether its params are all finite} of every checkpoint in <workdir>/policy/checkpoints."""
  import jax  # pylint: disable=import-outside-toplevel
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  config = rundir.load_config(workdir)
  encoder = encoders.build_encoder(config, workdir)
  with Checkpointer(rundir.checkpoints(rundir.policy_dir(workdir))) as ckpt:
    steps = ckpt.all_steps()
  return {s: all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(
      bc.load_params(config, workdir, encoder.num_tokens, encoder.token_dim, s)[1])) for s in steps}


def _stage_state(workdir, stage):
  with open(os.path.join(workdir, "stages.json")) as f:
    return json.load(f)[stage]["state"]


# ------------------------------------------------------------------------------------- divergence and --redo


@pytest.fixture(scope="module")
def sequences(data_dir, tmp_path_factory):
  """The issue's two sequences on one workdir, and the way forward, each step's outcome recorded for the tests:
  learning_rate=1e6 (diverges), the same command with the default rate (refused), then with --redo=train_policy
  (trains again, 8 steps: checkpoints 6 and 8). Returns the workdir, a finished run, and what each step left."""
  from roboshape.train.divergence import Diverged  # pylint: disable=import-outside-toplevel
  workdir = str(tmp_path_factory.mktemp("records_run") / "pick_state")
  out = {"workdir": workdir}
  with pytest.raises(Diverged) as e:
    stages.run(_config(data_dir, learning_rate=1e6, steps=8, checkpoint_every=1), workdir)
  out.update(diverged=str(e.value), diverged_checkpoints=_checkpoints_finite(workdir),
             diverged_stage=_stage_state(workdir, "train_policy"),
             diverged_summary=os.path.exists(os.path.join(rundir.policy_dir(workdir), "summary.json")))
  before = _snapshot(workdir)
  with pytest.raises(UserError) as e:
    stages.run(_config(data_dir, steps=8), workdir)
  out.update(refused=str(e.value), refused_changed=_snapshot(workdir) != before,
             refused_config=rundir.load_config(workdir).policy.train.learning_rate)
  stages.run(_config(data_dir, steps=8), workdir, redo=("train_policy",))
  return out


@pytest.fixture(scope="module")
def trained(sequences):
  """The workdir of a finished run of `_config(steps=8)` (checkpoints 6 and 8, policy/fingerprint.json)."""
  return sequences["workdir"]


def test_a_diverging_policy_stops_at_once_keeping_only_finite_checkpoints(sequences):
  """learning_rate=1e6: one line naming the stage, the step and the field; the checkpoints left are all finite,
  the last one just before the step; the stage is not done."""
  message = sequences["diverged"]
  assert "\n" not in message and message.startswith("train_policy: the policy's loss is nan")
  step = int(message.split(" at step ")[1].split(";")[0])
  assert 1 < step < 8
  assert "--config.policy.train.learning_rate (now 1000000.0)" in message and "--redo=train_policy" in message
  finite = sequences["diverged_checkpoints"]
  assert finite and all(finite.values()) and max(finite) == step - 1        # the last finite one is kept
  assert f"the last checkpoint, step {step - 1}, is finite and kept" in message
  assert sequences["diverged_stage"] != "done" and not sequences["diverged_summary"]


def test_the_rerun_with_a_sane_rate_is_refused_and_changes_nothing(sequences):
  message = sequences["refused"]
  lr = _config("").policy.train.learning_rate
  assert "\n" not in message and "the train_policy stage" in message
  assert f"policy.train.learning_rate: 1000000.0 there, {lr!r} in this config" in message
  assert "another --workdir" in message and "--redo=train_policy" in message
  assert "policy.with-learning_rate=1000000.0" in message and message.endswith("Nothing was changed.")
  assert not sequences["refused_changed"] and sequences["refused_config"] == 1e6     # config.json included


def test_redo_sets_the_attempt_aside_and_trains_again_and_config_json_agrees(sequences):
  workdir = sequences["workdir"]
  aside = os.path.join(workdir, "policy.with-learning_rate=1000000.0")
  assert _fields(aside)["policy.train.learning_rate"] == 1e6                 # the attempt, as it was
  assert _stage_state(workdir, "train_policy") == "done"
  assert _checkpoints_finite(workdir) == {6: True, 8: True}
  policy, config = _fields(rundir.policy_dir(workdir)), rundir.load_config(workdir)
  lr = _config("").policy.train.learning_rate
  assert policy["policy.train.learning_rate"] == config.policy.train.learning_rate == lr
  assert policy["policy.train.batch_size"] == config.policy.train.batch_size and policy["seed"] == config.seed


def test_a_check_of_the_parameters_keeps_a_non_finite_checkpoint_from_being_written(monkeypatch, tmp_path):
  """Metrics that look finite do not let non-finite parameters reach a checkpoint."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  from roboshape.train.divergence import Diverged  # pylint: disable=import-outside-toplevel
  state = {"step": jnp.int32(3), "params": {"w": jnp.array([1.0, jnp.inf])}}
  with Checkpointer(str(tmp_path / "checkpoints")) as ckpt:
    with pytest.raises(Diverged, match=r"^train_policy: the policy's parameters are not finite \(NaN or inf\) at "
                                       r"step 3; .*no checkpoint was written yet"):
      bc._save_finite(ckpt, 3, state, 1e-3)          # pylint: disable=protected-access
    assert ckpt.all_steps() == []


# ---------------------------------------------------------------------------------- fingerprints of a finished run


def test_a_finished_run_rerun_with_other_settings_is_refused_naming_each_field_and_nothing_changes(
    trained, data_dir, tmp_path):
  workdir = _copy(trained, tmp_path)
  before = _snapshot(workdir)
  other = _config(data_dir, batch_size=2)
  other.policy.history, other.seed = 3, 7
  with pytest.raises(UserError) as e:
    stages.run(other, workdir)
  message = str(e.value)
  assert "\n" not in message and message.startswith(f"{workdir} holds what the train_policy stage made with other "
                                                     "settings (")
  for said in ("policy.history: 2 there, 3 in this config", "policy.train.batch_size: 4 there, 2 in this config",
               "seed: 0 there, 7 in this config"):
    assert said in message
  assert "use another --workdir, or run again with --redo=train_policy" in message
  assert _snapshot(workdir) == before                        # config.json included

  unchanged = _config(data_dir, steps=8)                     # the same command: skips, nothing refused
  unchanged.policy.eval.action = "sample"                    # control settings are the evaluation's, not a difference
  stages.run(unchanged, workdir)
  assert _fields(rundir.policy_dir(workdir)) == _fields(rundir.policy_dir(trained))


def test_more_steps_resume_and_an_old_workdir_is_adopted_once(trained, data_dir, tmp_path, capsys):
  """A workdir written before fingerprints (no fingerprint.json) is read with its config.json as the record, said
  once; it resumes to more steps (no refusal), and with other settings it is refused like any other."""
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  workdir = _copy(trained, tmp_path)
  policy_dir = rundir.policy_dir(workdir)
  os.remove(rundir.fingerprint_path(policy_dir))
  with pytest.raises(UserError, match=r"policy.train.learning_rate: 0.0001 there, 0.5 in this config"):
    stages.run(_config(data_dir, learning_rate=0.5), workdir)
  assert not os.path.exists(rundir.fingerprint_path(policy_dir))
  capsys.readouterr()
  stages.run(_config(data_dir, steps=10), workdir)
  out = capsys.readouterr().out
  assert out.count("was written before stages recorded the config fields they read") == 1
  assert "already trained" not in out
  with Checkpointer(rundir.checkpoints(policy_dir)) as ckpt:
    assert ckpt.all_steps() == [8, 10]                       # resumed from step 8
  assert _fields(policy_dir) == _fields(rundir.policy_dir(trained))
  assert rundir.load_config(workdir).policy.train.steps == 10
  stages.run(_config(data_dir, steps=10), workdir)
  out = capsys.readouterr().out
  assert "written before" not in out and "already trained to step 10" in out


def test_redo_names_only_stages_it_takes_and_the_config_runs(data_dir, tmp_path):
  workdir = str(tmp_path / "run")
  with pytest.raises(UserError, match="evaluate is not a stage --redo takes"):
    stages.run(_config(data_dir), workdir, redo=("evaluate",))
  with pytest.raises(UserError, match="config.stages does not run pretrain"):
    stages.run(_config(data_dir), workdir, redo=("pretrain",))
  with pytest.raises(UserError, match="--redo=collect sets aside only a dataset in the run's own workdir"):
    config = _config(data_dir)
    config.stages = ("collect", "train_policy")
    stages.run(config, workdir, redo=("collect",))
  assert not os.path.exists(workdir)


def test_the_aside_name_says_what_the_output_was_made_with_and_never_overwrites(tmp_path):
  from roboshape.train import fingerprint  # pylint: disable=import-outside-toplevel
  policy = str(tmp_path / "policy")
  diff = [("policy.train.learning_rate", 1e6, 1e-3), ("policy.history", 10, 2), ("seed", 1, 2)]
  assert fingerprint.aside_name(policy, diff) == f"{policy}.with-learning_rate=1000000.0,history=10,+1"
  os.makedirs(f"{policy}.with-learning_rate=1000000.0,history=10,+1")
  assert fingerprint.aside_name(policy, diff) == f"{policy}.with-learning_rate=1000000.0,history=10,+1.2"


# ---------------------------------------------------------------------------- non-finite features, actions, states


def test_non_finite_names_the_first_bad_step_of_actions_then_states():
  episode = _synthetic_episode(3, task="pick", state=True)
  assert data_lib.non_finite(episode) is None
  episode["state"][5, 2] = np.inf
  assert data_lib.non_finite(episode) == "states at step 5"
  episode["action"][2, 0] = np.nan
  assert data_lib.non_finite(episode) == "actions at step 2"
  assert data_lib.non_finite({k: v for k, v in episode.items() if k != "state"}) == "actions at step 2"


def test_the_reader_refuses_an_episode_with_non_finite_actions_naming_it(tmp_path):
  bad = _synthetic_episode(7, task="pick", state=True)
  bad["action"][3] = np.nan
  path = rlds.write_dataset(str(tmp_path / "roboshape_pick" / "1.0.0"),
                            {"train": [_synthetic_episode(6, task="pick", state=True), bad],
                             "val": [_synthetic_episode(1_000_000, task="pick", state=True)]})
  with pytest.raises(UserError) as e:
    list(reader.read_episodes(path, "train"))
  assert str(e.value).startswith(f"episode seed 7 of split 'train' in the dataset at {path} has non-finite actions "
                                 "at step 3 (NaN or inf)") and "\n" not in str(e.value)
  assert [ep["seed"] for ep in reader.read_episodes(path, "val")] == [1_000_000]


class _Pool:
  """Stands in for roboshape.sim.SimPool: synthetic pick episodes with states, seed `broken`'s state NaN at step 1
  (a success, unless `fails`)."""

  def __init__(self, broken, fails=False):
    self.broken, self.fails = broken, fails

  def collect(self, seeds):
    for seed in seeds:
      episode = _synthetic_episode(seed, task="pick", state=True)
      if seed == self.broken:
        episode["state"][1] = np.nan
        episode["success"] = episode["terminated"] = not self.fails
      yield episode


def _collect_config():
  config = common.get_config("pick", "state", "tiny")
  config.data.train_episodes, config.env.resolution = 4, 16
  return config


def test_collection_refuses_a_successful_episode_with_non_finite_states_naming_its_seed(tmp_path):
  config = _collect_config()
  path = str(tmp_path / "roboshape_pick" / "1.0.0")
  with pytest.raises(UserError) as e:
    collect.collect_dataset(_Pool(broken=2), path, collect.config_summary(config), collect.split_targets(config),
                            progress=False)
  assert str(e.value).startswith(f"the expert's episode of seed 2 (train split of {path}) has non-finite states at "
                                 "step 1 (NaN or inf): nothing of it was written") and "\n" not in str(e.value)
  state = rlds.load_state(path)
  assert not state["complete"]
  assert 2 not in [s for shard in state["splits"]["train"]["shards"] for s in shard["seeds"]]
  failed = str(tmp_path / "failed" / "roboshape_pick" / "1.0.0")      # a failure is never stored, NaN or not
  collect.collect_dataset(_Pool(broken=2, fails=True), failed, collect.config_summary(config),
                          collect.split_targets(config), progress=False)
  assert rlds.load_state(failed)["complete"]


def _toy_encoder(scale):
  """Frames -> one token of 4 values, the pixels' mean times `scale` (NaN or huge on demand)."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel

  def step(params, state, frames):
    x = frames.reshape(frames.shape[0], -1).astype(jnp.float32).mean(axis=1) / 255.0 + 1.0
    return (x * params["scale"])[:, None, None] * jnp.ones((1, 1, 4)), state

  return FrozenEncoder(name="toy", params={"scale": jnp.float32(scale)}, step=step, init_state=lambda b: (),
                       num_tokens=1, token_dim=4, identity=f"toy-{scale}")


@pytest.mark.parametrize("scale, dtype, expected", [
    (np.nan, "float32", r"^the toy encoder \(toy-nan\) gives non-finite features \(NaN or inf\) for episode seed \d+ "
                        r"\(frame 0 of \d+\); nothing of their shard was written"),
    (1e6, "float16", r"^the toy encoder's features of episode seed \d+ \(frame 0 of \d+\) overflow "
                     r"policy.cache_dtype='float16' \(largest \|value\| .*\): cache them as float32 "
                     r"\(--config.policy.cache_dtype=float32\); nothing of their shard was written"),
])
def test_the_cache_refuses_non_finite_features_naming_the_episode(tmp_path, scale, dtype, expected):
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  config = _collect_config()
  config.policy.cache_dtype = dtype
  workdir = str(tmp_path / "run")
  rlds.write_dataset(data_lib.dataset_path(config, workdir),
                     {"train": [_synthetic_episode(s, task="pick") for s in range(2)],
                      "val": [_synthetic_episode(1_000_000, task="pick")]})
  encoder = _toy_encoder(scale)
  with pytest.raises(UserError, match=expected) as e:
    cache.build(config, workdir, encoder)
  assert "\n" not in str(e.value)
  folder = cache.feature_dir(config, workdir, encoder)
  assert not os.path.exists(os.path.join(folder, "manifest.json"))
  assert not [n for _, _, names in os.walk(folder) for n in names if n.endswith(".npz")]


# --------------------------------------------------------------------------------- a policy that cannot act


def test_a_policy_with_non_finite_parameters_or_actions_is_blamed_in_one_line(trained, tmp_path, monkeypatch):
  import jax  # pylint: disable=import-outside-toplevel
  from roboshape.envs import state as state_lib  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  workdir = _copy(trained, tmp_path)
  policy_dir = rundir.policy_dir(workdir)
  blame = (f"It is the policy's fault, not the simulator's: checkpoint step 8 in {rundir.checkpoints(policy_dir)}, "
           "trained with policy.train.learning_rate=0.0001, ")
  policy = bc.acting_policy(workdir)                     # a finite one acts, its actions checked
  policy.reset(batch_size=2)
  frames = {"state": np.zeros((2, state_lib.DIM), np.float32), "image": np.zeros((2, 16, 16, 3), np.uint8)}
  assert np.isfinite(policy.act_batch(frames)).all()
  policy._policy.params = jax.tree.map(lambda x: x * np.nan, policy.params)   # pylint: disable=protected-access
  with pytest.raises(UserError) as e:
    policy.act_batch(frames)
  message = str(e.value)
  assert "\n" not in message and message.startswith(f"the policy in {policy_dir} cannot act: its actions are not "
                                                    "finite (NaN or inf) for env(s) [0, 1] of the batch")
  assert blame in message and f"({rundir.fingerprint_path(policy_dir)})" in message

  real = bc.load_policy

  def poisoned(*args, **kwargs):
    loaded = real(*args, **kwargs)
    loaded.params = jax.tree.map(lambda x: x * np.nan, loaded.params)
    return loaded

  monkeypatch.setattr(bc, "load_policy", poisoned)
  with pytest.raises(UserError) as e:
    bc.acting_policy(workdir)
  message = str(e.value)
  assert "\n" not in message and message.startswith(f"the policy in {policy_dir} cannot act: its parameters are not "
                                                    "finite (NaN or inf). ")
  assert blame in message and "--redo=train_policy" in message
