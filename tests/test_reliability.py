"""Reliability: damaged dataset shards are re-collected, damaged checkpoints fall back to an older step (an intact one
of another config is refused, never set aside), a policy refuses an encoder it was not trained on, videos are
written atomically and rebuilt on resume, and an interrupt ends in one line. Tiny shapes throughout: the whole file
runs in well under a minute on 2 CPU cores."""
import json
import os
import shutil

import pytest

from configs import common
from conftest import _synthetic_episode
from roboshape import data as data_lib
from roboshape.errors import UserError
from roboshape.data import collect
from roboshape.data import reader
from roboshape.data import rlds

pytestmark = pytest.mark.usefixtures("cheap_xla_module")     # compile-bound: XLA's cheap optimisation level


# ------------------------------------------------------------------------------------------------ dataset shards


class FakePool:
  """Stands in for roboshape.sim.SimPool: synthetic episodes (seeds % 4 == 1 fail); records the seeds asked for."""

  def __init__(self, env_version="synthetic-1", brightness=0):
    self.env_version, self.brightness = env_version, brightness
    self.requested = []

  def collect(self, seeds):
    for seed in seeds:
      self.requested.append(seed)
      episode = _synthetic_episode(seed, success=seed % 4 != 1, state=True)
      episode["image"] = episode["image"] + self.brightness     # another simulator: other pixels
      yield episode


def _data_config():
  config = common.get_config("push", "savi", "tiny")
  config.data.train_episodes, config.env.resolution = 4, 16
  return config


def _collect(config, path, pool):
  return collect.collect_dataset(pool, path, collect.config_summary(config), collect.split_targets(config),
                                 progress=False)


def _files(path):
  """{shard file: bytes} of a dataset."""
  out = {}
  for name in sorted(os.listdir(path)):
    if ".tfrecord-" in name:
      with open(os.path.join(path, name), "rb") as f:
        out[name] = f.read()
  return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
  """A complete dataset collected with FakePool (4 train shards of one episode, 1 val shard): (config, path)."""
  config = _data_config()
  path = str(tmp_path_factory.mktemp("reference") / "roboshape_push" / "1.0.0")
  _collect(config, path, FakePool())
  return config, path


def _damaged_copy(dataset, tmp_path):
  """A copy of the dataset with train shard 1 truncated, shard 2 deleted and shard 3 with flipped bytes."""
  _, path = dataset
  copy = str(tmp_path / "roboshape_push" / "1.0.0")
  shutil.copytree(path, copy)
  shards = rlds.load_state(copy)["splits"]["train"]["shards"]
  with open(os.path.join(copy, shards[1]["file"]), "r+b") as f:
    f.truncate(shards[1]["num_bytes"] // 2)
  os.remove(os.path.join(copy, shards[2]["file"]))
  with open(os.path.join(copy, shards[3]["file"]), "r+b") as f:
    f.seek(shards[3]["num_bytes"] // 2)
    f.write(b"\x00\xff\x00\xff")
  return copy, shards


def test_readers_name_a_damaged_shard_in_one_line(dataset, tmp_path):
  _, path = dataset
  copy = str(tmp_path / "flipped")
  shutil.copytree(path, copy)
  shard = rlds.load_state(copy)["splits"]["train"]["shards"][2]
  with open(os.path.join(copy, shard["file"]), "r+b") as f:           # same size: found only when decoding fails
    f.seek(shard["num_bytes"] // 2)
    f.write(b"\x00\xff\x00\xff")
  with pytest.raises(UserError) as e:
    list(reader.read_episodes(copy, "train"))
  message = str(e.value)
  assert "\n" not in message and shard["file"] in message and "corrupted" in message
  assert f"python -m roboshape.data.validate {copy}" in message
  os.remove(os.path.join(copy, shard["file"]))                       # missing: found before reading
  with pytest.raises(UserError, match=f"shard .*{shard['file']} is missing: run the collect stage again"):
    reader.read_episodes(copy, "train")
  with pytest.raises(UserError, match="is missing"):
    next(reader.clip_batches(copy, "train", clip_length=2, batch_size=2))


def test_collect_recollects_exactly_the_damaged_shards(dataset, tmp_path):
  config, path = dataset
  copy, shards = _damaged_copy(dataset, tmp_path)
  before = {f: os.path.getmtime(os.path.join(copy, f)) for f in os.listdir(copy)}
  pool = FakePool()
  report = _collect(config, copy, pool)
  assert report["already_complete"] and report["repaired"] == [s["file"] for s in shards[1:4]]
  assert pool.requested == [seed for s in shards[1:4] for seed in s["seeds"]]          # their seeds, nothing else
  assert _files(copy) == _files(path)                                                  # byte for byte
  untouched = [f for f in before if f not in report["repaired"] and f != ".collect.lock"]
  assert all(os.path.getmtime(os.path.join(copy, f)) == before[f] for f in untouched)
  assert not any(name.endswith(".tmp") for name in os.listdir(copy))
  assert [e["seed"] for e in reader.read_episodes(copy, "train")] == [s["seeds"][0] for s in shards]


def test_collect_stage_repairs_a_complete_dataset_and_skips_an_intact_one(dataset, tmp_path, monkeypatch, capsys):
  import roboshape.sim  # pylint: disable=import-outside-toplevel
  config, path = dataset
  workdir = str(tmp_path / "run")
  started = []

  class Pool(FakePool):
    def __init__(self, spec, num_workers):
      super().__init__()
      started.append((spec.task, num_workers))

    def __enter__(self):
      return self

    def __exit__(self, *exc):
      pass

  monkeypatch.setattr(roboshape.sim, "SimPool", Pool)
  shutil.copytree(os.path.dirname(os.path.dirname(path)), os.path.join(workdir, "data"))
  copy = data_lib.dataset_path(config, workdir)
  collect.run(config, workdir)
  assert not started and "already holds the complete dataset" in capsys.readouterr().out
  state = rlds.load_state(copy)
  os.remove(os.path.join(copy, state["splits"]["val"]["shards"][0]["file"]))
  collect.run(config, workdir)
  out = capsys.readouterr().out
  assert started == [("push", config.sim.num_workers)]
  assert "is missing: re-collecting its 1 episode(s)" in out and "re-collected 1 damaged shard(s)" in out
  assert f"dataset complete: {copy}" in out
  assert _files(copy) == _files(path)


def test_a_shard_that_cannot_be_made_again_is_refused_and_left_alone(dataset, tmp_path):
  config, _ = dataset
  copy, shards = _damaged_copy(dataset, tmp_path)
  before = _files(copy)
  with pytest.raises(UserError) as e:
    _collect(config, copy, FakePool(brightness=1))
  message = str(e.value)
  assert "\n" not in message and shards[1]["file"] in message and f"{copy} is left as it is" in message
  assert "repair it with the roboshape that collected it" in message and "delete" not in message.lower()
  assert _files(copy) == before and not any(name.endswith(".tmp") for name in os.listdir(copy))
  with pytest.raises(UserError, match=r"env version 'synthetic-1', this one is 'synthetic-2'\) can make it again: "
                     r"run the same command with the roboshape of that version") as e:
    _collect(config, copy, FakePool(env_version="synthetic-2"))
  assert "delete" not in str(e.value).lower()
  assert _files(copy) == before


# ------------------------------------------------------------------------------------ checkpoints and the encoder

RES, K, D = 8, 2, 4


def _toy_encoder(identity="toy-v1"):
  """A fixed random projection of each frame into K tokens (no memory); `identity` names its weights."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  w = jax.random.normal(jax.random.PRNGKey(3), (RES * RES * 3, K * D)) / 16.0

  def step(params, state, frames):
    x = frames.reshape(frames.shape[0], -1).astype(jnp.float32) / 255.0
    return jnp.tanh(x @ params["w"]).reshape(-1, K, D), state

  return FrozenEncoder(name="toy", params={"w": w}, step=step, init_state=lambda b: (), num_tokens=K,
                       token_dim=D, identity=identity)


def _policy_config(steps=20):
  config = common.get_config("pick", "savi", "tiny")
  config.env.resolution = RES
  p = config.policy
  p.history, p.width, p.num_layers, p.num_heads, p.dropout = 2, 16, 1, 2, 0.0
  p.train.update(dict(steps=steps, batch_size=4, warmup_steps=2, log_every=10, eval_every=10,
                      checkpoint_every=10, val_batch_size=4))
  return config


def features_run(workdir):
  """Writes into `workdir` a tiny pick dataset (2 train + the same 2 as val episodes), the run's config.json and the
  toy encoder's feature cache: (config, the feature cache's path)."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  config = _policy_config()
  rng = np.random.default_rng(0)
  episodes = [dict(task="pick", level="train", seed=s, success=True, env_version="test", terminated=True,
                   image=rng.integers(0, 255, (7, RES, RES, 3), dtype=np.uint8),
                   segmentation=np.zeros((7, RES, RES), np.uint8),
                   action=rng.uniform(-1, 1, (6, 7)).astype(np.float32), reward=np.zeros((6,), np.float32))
              for s in range(2)]
  rlds.write_dataset(data_lib.dataset_path(config, workdir), {"train": episodes, "val": episodes})
  with open(os.path.join(workdir, "config.json"), "w") as f:
    f.write(config.to_json())
  return config, cache.build(config, workdir, _toy_encoder())


@pytest.fixture(scope="module")
def policy_run(tmp_path_factory):
  """A workdir with a toy-encoder feature cache (`features_run`) and a tiny policy trained 20 steps (checkpoints 10
  and 20)."""
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  workdir = str(tmp_path_factory.mktemp("policy_run"))
  config, features = features_run(workdir)
  bc.train(config, workdir, features)
  return dict(workdir=workdir, config=config, features=os.path.basename(features))


def _copy_run(policy_run, tmp_path):
  """A private copy of the trained workdir: (workdir, its feature directory)."""
  workdir = str(tmp_path / "run")
  shutil.copytree(policy_run["workdir"], workdir)
  return workdir, os.path.join(workdir, "features", policy_run["features"])


def _damage_step(workdir, step):
  """Truncates to half every file of each item (the train state, the params) of one policy checkpoint: orbax may
  spread an item's arrays over several data files (more of them on a busy machine), so every one is cut."""
  root = os.path.join(workdir, "policy", "checkpoints", str(step))
  for item in sorted(n for n in os.listdir(root) if os.path.isdir(os.path.join(root, n))):
    for path in [os.path.join(d, n) for d, _, names in os.walk(os.path.join(root, item)) for n in names]:
      with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def _params(config, workdir, step=None):
  import jax  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  return [np.asarray(x) for x in jax.tree.leaves(bc.load_params(config, workdir, K, D, step)[1])]


def _same(a, b):
  import numpy as np  # pylint: disable=import-outside-toplevel
  return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))


def test_a_damaged_checkpoint_falls_back_to_the_older_step(policy_run, tmp_path, capsys):
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  config = policy_run["config"]
  workdir, features = _copy_run(policy_run, tmp_path)
  trained, at_10 = _params(config, workdir), _params(config, workdir, step=10)
  ckpt_dir = os.path.join(workdir, "policy", "checkpoints")
  _damage_step(workdir, 20)
  capsys.readouterr()
  assert _same(_params(config, workdir), at_10)            # loading: falls back, leaves the files as they are
  warning = (f"[roboshape] checkpoint step 20 in {ckpt_dir} does not restore (")
  err = capsys.readouterr().err
  assert warning in err and err.strip().endswith("falling back to step 10") and len(err.strip().splitlines()) == 1
  assert sorted(os.listdir(ckpt_dir)) == ["10", "20"]
  with pytest.raises(UserError, match="checkpoint step 20 in .* does not restore .*load another step"):
    _params(config, workdir, step=20)
  summary = bc.train(config, workdir, features)           # resuming: from step 10 again, to the same step 20
  err = capsys.readouterr().err
  assert warning in err and "falling back to step 10" in err and "damaged_step_20" in err
  assert sorted(os.listdir(ckpt_dir)) == ["10", "20", "damaged_step_20"]
  assert summary["step"] == 20 and _same(_params(config, workdir), trained)


def test_an_interrupted_policy_keeps_its_steps_and_resumes_to_the_uninterrupted_params(policy_run, tmp_path,
                                                                                        monkeypatch):
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  config = _policy_config(steps=30)                  # both copies resume from step 20
  straight, features = _copy_run(policy_run, tmp_path / "straight")
  bc.train(config, straight, features)
  interrupted, features = _copy_run(policy_run, tmp_path / "interrupted")

  bar = bc.progress.bar

  def stop_after_five(*args, **kwargs):              # Ctrl-C once five steps are done (no checkpoint is due)
    for i, step in enumerate(bar(*args, **kwargs)):
      if i == 5:
        raise KeyboardInterrupt
      yield step

  with monkeypatch.context() as stop:
    stop.setattr(bc.progress, "bar", stop_after_five)
    with pytest.raises(KeyboardInterrupt):
      bc.train(config, interrupted, features)
  with Checkpointer(os.path.join(interrupted, "policy", "checkpoints")) as ckpt:
    assert ckpt.latest_step() == 25
  bc.train(config, interrupted, features)
  assert _same(_params(config, interrupted), _params(config, straight))
  assert not _same(_params(config, interrupted, 25), _params(config, straight))


def test_no_checkpoint_that_restores_is_one_line(policy_run, tmp_path):
  workdir, _ = _copy_run(policy_run, tmp_path)
  _damage_step(workdir, 10)
  _damage_step(workdir, 20)
  with pytest.raises(UserError) as e:
    _params(policy_run["config"], workdir)
  message = str(e.value)
  assert "\n" not in message and message.startswith("no checkpoint in ") and "restores (step 20:" in message
  assert "every one is damaged" in message                     # only then does it say to move them away
  assert sorted(os.listdir(os.path.join(workdir, "policy", "checkpoints"))) == ["10", "20"]   # nothing moved


def test_an_intact_checkpoint_of_another_config_is_refused_naming_that_config_and_never_set_aside(
    policy_run, tmp_path, capsys):
  """A checkpoint that reads as saved but not into this config's structure (here another policy width) is not
  damaged: loading and resuming stop with one line that names the safe action first, no older step is tried, and
  nothing is set aside, also when a newer step is damaged."""
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  workdir, features = _copy_run(policy_run, tmp_path)
  ckpt_dir = os.path.join(workdir, "policy", "checkpoints")
  wider = _policy_config(steps=30)
  wider.policy.width = 32
  safe = "run with the config these checkpoints were trained with (the workdir's config.json"
  for damaged in (False, True):
    if damaged:
      _damage_step(workdir, 20)                                # 20 is damaged, 10 intact but of another config
    for attempt, step, falls_back in ((lambda: _params(wider, workdir), 10 if damaged else 20, damaged),
                                      (lambda: _params(wider, workdir, step=10), 10, False),
                                      (lambda: bc.train(wider, workdir, features), 10 if damaged else 20, damaged)):
      capsys.readouterr()
      with pytest.raises(UserError) as e:
        attempt()
      message, err = str(e.value), capsys.readouterr().err
      assert message.startswith(safe) and "\n" not in message, message
      assert f"checkpoint step {step} in {ckpt_dir} is intact" in message
      assert "move" not in message.replace("nothing was moved", "") and "damaged" not in message
      assert ("falling back to step 10" in err) == falls_back and "damaged_step" not in err
      assert sorted(os.listdir(ckpt_dir)) == ["10", "20"]      # nothing set aside


def test_a_policy_refuses_an_encoder_it_was_not_trained_on(policy_run, tmp_path, monkeypatch):
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  config = policy_run["config"]
  workdir, _ = _copy_run(policy_run, tmp_path)
  with open(os.path.join(workdir, "policy", "encoder.json")) as f:
    assert json.load(f) == dict(encoder="toy", identity="toy-v1", features=policy_run["features"])
  monkeypatch.setattr(encoders, "build_encoder", lambda config, workdir: _toy_encoder("toy-v1"))
  assert bc.load_policy(workdir).encoder.identity == "toy-v1"         # the encoder it was trained on: fine
  monkeypatch.setattr(encoders, "build_encoder", lambda config, workdir: _toy_encoder("toy-v2"))
  policy_dir = os.path.join(workdir, "policy")
  message = (f"the policy in {policy_dir} was trained on encoder toy-v1, the workdir's encoder is now toy-v2: "
             "its actions would be meaningless, and the policy is left as it is. To train one on the current "
             f"encoder, rename {policy_dir} (e.g. to {policy_dir}.old, which keeps it)")
  before = sorted(os.listdir(policy_dir))
  for attempt in (lambda: bc.load_policy(workdir),                                   # load_policy
                  lambda: closed_loop.run(config, workdir),                          # evaluate
                  lambda: bc.run(config, workdir),                                   # train_policy (resume)
                  lambda: bc.train(config, workdir, cache.build(config, workdir, _toy_encoder("toy-v2")))):
    with pytest.raises(UserError) as e:
      attempt()
    assert str(e.value).startswith(message) and "\n" not in str(e.value) and "delete" not in str(e.value).lower()
  assert sorted(os.listdir(policy_dir)) == before


def test_a_full_disk_in_train_policy_is_one_line_and_the_same_command_resumes(policy_run, tmp_path, monkeypatch,
                                                                              caplog, capfd):
  """The disk fills while the train_policy stage caches its features, then while it saves a checkpoint: each time
  one DiskFull line naming the stage and what it could not write, nothing half-written that a rerun could take for
  complete (no shard's temporary file, no manifest, the half-saved step never listed), the last checkpoint restores
  as it was, and orbax's threads log nothing. With space again, the same call resumes and finishes."""
  import errno  # pylint: disable=import-outside-toplevel
  import logging  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel
  from conftest import fill_disk_at_checkpoint  # pylint: disable=import-outside-toplevel
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  from roboshape.errors import DiskFull  # pylint: disable=import-outside-toplevel
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  workdir, _ = _copy_run(policy_run, tmp_path)        # trained to step 20; the copy's dataset gets a cache of its own
  monkeypatch.setattr(encoders, "build_encoder", lambda config, workdir: _toy_encoder())
  config = _policy_config(steps=30)
  trained, ckpt_dir = _params(config, workdir), os.path.join(workdir, "policy", "checkpoints")
  features = cache.feature_dir(config, workdir, _toy_encoder())
  summary = os.path.join(workdir, "policy", "summary.json")

  def stage():         # as stages.run runs a stage (whose config check refuses the toy encoder's 8x8 frames)
    with stages.disk_full_is_one_line("the train_policy stage", workdir):
      bc.run(config, workdir)

  def line(path):
    return (f"disk full while the train_policy stage wrote {path}: what it wrote completely is kept. Free some "
            f"space on that disk (keep {workdir}: the run resumes from it) and run the same command again to "
            "resume.")

  real_savez = np.savez

  def savez_until_full(f, **arrays):                # the val shard meets the full disk half-way through
    if f"{os.sep}val{os.sep}" not in f.name:
      return real_savez(f, **arrays)
    f.write(b"PK half a shard")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  with monkeypatch.context() as full:
    full.setattr(np, "savez", savez_until_full)
    with pytest.raises(DiskFull) as e:
      stage()
  assert str(e.value) == line(os.path.join(features, "val", "shard_00000.npz"))
  assert os.listdir(os.path.join(features, "val")) == [] and not os.path.exists(os.path.join(features, "manifest.json"))
  train_shard = os.path.join(features, "train", "shard_00000.npz")
  kept = os.stat(train_shard).st_mtime_ns
  with monkeypatch.context() as full:
    fill_disk_at_checkpoint(full, 30)
    with pytest.raises(DiskFull) as e:
      stage()                                       # the cache is finished, then training meets the full disk
  assert str(e.value) == line(ckpt_dir) and os.stat(train_shard).st_mtime_ns == kept
  assert os.path.exists(os.path.join(features, "manifest.json"))
  assert any(name.startswith("30.") for name in os.listdir(ckpt_dir))        # the half-saved step's folder ...
  with Checkpointer(ckpt_dir) as ckpt:
    assert ckpt.all_steps() == [10, 20]                                      # ... is not a step
  assert _same(_params(config, workdir), trained)
  with open(summary) as f:
    assert json.load(f)["step"] == 20
  assert not [r for r in caplog.records if r.levelno >= logging.ERROR] and "Traceback" not in capfd.readouterr().err
  stage()                                           # space again: the same command resumes from step 20
  with Checkpointer(ckpt_dir) as ckpt:
    assert ckpt.all_steps() == [20, 30]
  assert not [name for name in os.listdir(ckpt_dir) if "tmp" in name]
  with open(summary) as f:
    assert json.load(f)["step"] == 30


# -------------------------------------------------------------------------------------------- videos and signals


def test_videos_are_atomic_and_rebuilt_when_missing(tmp_path, monkeypatch):
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel
  from test_eval import FakePolicy, FakePool, _config  # pylint: disable=import-outside-toplevel
  from roboshape.eval import closed_loop  # pylint: disable=import-outside-toplevel
  from roboshape.eval import videos  # pylint: disable=import-outside-toplevel
  config = _config(levels=("train",), num_seeds=1, rollouts=2)
  workdir, video_dir = str(tmp_path), str(tmp_path / "eval" / "videos")
  pools = []
  make_pool = lambda level: pools.append(FakePool()) or pools[-1]
  closed_loop.evaluate(config, workdir, FakePolicy(), make_pool)
  assert sorted(os.listdir(video_dir)) == ["train_s1000_success.gif", "train_s1000_success.mp4"]
  with open(tmp_path / "eval" / "results.json") as f:
    results = json.load(f)
  # A kill while writing leaves only a temporary file; the resumed evaluation deletes it and records the video again.
  for name in os.listdir(video_dir):
    os.remove(os.path.join(video_dir, name))
  with open(os.path.join(video_dir, "train_s1000_success.tmp.mp4"), "wb") as f:
    f.write(b"half a video")
  pools.clear()
  closed_loop.evaluate(config, workdir, FakePolicy(), make_pool)
  assert [p.reset_seeds for p in pools] == [[1000]]                   # only the rollout of the missing video
  assert sorted(os.listdir(video_dir)) == ["train_s1000_success.gif", "train_s1000_success.mp4"]
  with open(tmp_path / "eval" / "results.json") as f:
    assert json.load(f) == results                                    # the logged results stand
  pools.clear()
  closed_loop.evaluate(config, workdir, FakePolicy(), make_pool)
  assert not pools                                                    # nothing missing: no simulator started
  # A writer that fails half-way leaves neither the video nor its temporary file.
  def fail(path, frames, **kwargs):
    with open(path, "wb") as f:
      f.write(b"partial")
    raise OSError("disk full")
  monkeypatch.setattr(imageio, "mimwrite", fail)
  assert videos.write_video(np.zeros((2, 8, 8, 3), np.uint8), str(tmp_path / "v")) == []
  assert not [n for n in os.listdir(tmp_path) if n.startswith("v.")]


_INTERRUPTED_RUN = """
import os, signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)   # as started from a terminal (not a background job)
sys.path.insert(0, {root!r})
import jax.numpy as jnp
from absl import logging
from ml_collections import config_flags
from roboshape import cli
from roboshape.checkpoint import Checkpointer
config_flags.DEFINE_config_file("config", None, "")

def main(argv):
  logging.set_verbosity(logging.WARNING)   # as launch.py
  with Checkpointer({ckpt!r}, keep=2) as ckpt:
    state = dict(w=jnp.ones((1 << 21,)))
    for step in range(1, 10**6):
      ckpt.save(step, state)            # asynchronous: a write is in flight when the signal comes
      time.sleep(0.05)

cli.exit_process(cli.run_app(main, [sys.argv[0], "--config={root}/configs/push_state.py:tiny"]))
"""


@pytest.mark.parametrize("signum,code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_an_interrupt_is_one_line_and_a_clean_exit(tmp_path, signum, code):
  import signal  # pylint: disable=import-outside-toplevel
  import subprocess  # pylint: disable=import-outside-toplevel
  import sys  # pylint: disable=import-outside-toplevel
  import time  # pylint: disable=import-outside-toplevel
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  ckpt = str(tmp_path / "checkpoints")
  script = _INTERRUPTED_RUN.format(root=root, ckpt=ckpt)
  proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True, env=dict(os.environ, JAX_PLATFORMS="cpu"))
  deadline = time.time() + 60
  while time.time() < deadline and not (os.path.isdir(ckpt) and len([n for n in os.listdir(ckpt)
                                                                      if n.isdigit()]) >= 2):
    time.sleep(0.05)
  proc.send_signal(getattr(signal, signum))
  _, err = proc.communicate(timeout=60)
  assert proc.returncode == code, err[-3000:]
  assert "Traceback" not in err and err.strip().splitlines()[-1] == (
      "roboshape: interrupted; run the same command to resume"), err[-3000:]
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  with Checkpointer(ckpt) as resumed:                                   # what was saved restores, at its last step
    latest = resumed.latest_step()
    assert resumed.restore_latest(dict(w=jnp.zeros((1 << 21,))))[1] == latest


def test_params_restore_alone_and_from_checkpoints_before_the_params_item(tmp_path):
  """A step holds the train state and the params as two items; serving restores the params alone. A checkpoint of
  an earlier version (one "default" item, the whole state) restores too, its params checked against the target."""
  import jax  # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  import numpy as np  # pylint: disable=import-outside-toplevel
  import orbax.checkpoint as ocp  # pylint: disable=import-outside-toplevel
  from roboshape.checkpoint import Checkpointer  # pylint: disable=import-outside-toplevel
  state = dict(step=jnp.array(3), params={"w": jnp.arange(4.0)}, opt_state={"mu": jnp.ones(4)})
  zeros = jax.tree.map(jnp.zeros_like, state)
  new, old = str(tmp_path / "new"), str(tmp_path / "old")
  with Checkpointer(new) as ckpt:
    ckpt.save(3, state)
  assert sorted(n for n in os.listdir(os.path.join(new, "3")) if not n.startswith(("_", "commit"))) == [
      "params", "state"]
  manager = ocp.CheckpointManager(old, options=ocp.CheckpointManagerOptions(create=True))   # the earlier format
  manager.save(3, args=ocp.args.StandardSave(state), force=True)
  manager.wait_until_finished()
  manager.close()
  for directory in (new, old):
    with Checkpointer(directory) as ckpt:
      params, step = ckpt.restore_params_latest(zeros["params"])
      assert step == 3 and np.array_equal(params["w"], np.arange(4.0))
      restored, _ = ckpt.restore_latest(zeros)
      assert np.array_equal(restored["opt_state"]["mu"], np.ones(4))
      with pytest.raises(UserError, match="does not restore"):
        ckpt.restore_params({"w": jnp.zeros(5)}, step=3)


def test_an_intact_step_of_other_shapes_is_refused_from_its_metadata_without_a_failed_read(tmp_path, monkeypatch):
  """A step whose metadata names the target's arrays with another shape is not read into the target (a read that
  fails leaves orbax's abandoned reads to settle, a second or more); it is refused as intact, naming the array and
  both shapes. A damaged step is still found damaged (it does not read as saved), and its failed reads settled."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape import checkpoint  # pylint: disable=import-outside-toplevel
  settles, settle = [], checkpoint._settle  # pylint: disable=protected-access
  monkeypatch.setattr(checkpoint, "_settle", lambda sink: settles.append(1) or settle(sink))
  directory = str(tmp_path / "ckpt")
  with checkpoint.Checkpointer(directory) as ckpt:
    ckpt.save(3, dict(step=jnp.array(3), params={"b": jnp.zeros(2), "w": jnp.arange(4.0)}))
  with checkpoint.Checkpointer(directory) as ckpt:
    with pytest.raises(UserError) as e:
      ckpt.restore_params_latest({"b": jnp.zeros(2), "w": jnp.zeros(5)})
  assert "step 3" in str(e.value) and "is intact" in str(e.value)
  assert "saved w of shape (4,), expected (5,)" in str(e.value) and settles == []
  for name in os.listdir(os.path.join(directory, "3", "params")):      # damage it: its arrays' data folders removed
    if name.startswith(("ocdbt", "d")) and os.path.isdir(os.path.join(directory, "3", "params", name)):
      shutil.rmtree(os.path.join(directory, "3", "params", name))
  with checkpoint.Checkpointer(directory) as ckpt:
    with pytest.raises(UserError, match="every one is damaged"):
      ckpt.restore_params_latest({"b": jnp.zeros(2), "w": jnp.zeros(5)})
  assert settles


def test_settling_after_a_failed_restore_frees_the_abandoned_reads_without_a_warning():
  """The coroutines of the reads a failed restore abandoned are freed by `_settle`'s collections; each would warn that
  it was never awaited (test runs record it, intermittently, as the collection happens there or later)."""
  import warnings  # pylint: disable=import-outside-toplevel
  from roboshape import checkpoint  # pylint: disable=import-outside-toplevel

  async def read():
    return None

  with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    cycle = [read()]          # an abandoned read, in a cycle: freed by a collection, not when dropped
    cycle.append(cycle)
    del cycle
    with checkpoint._quiet() as sink:                  # pylint: disable=protected-access
      checkpoint._settle(sink, quiet_polls=1, limit=1.0)  # pylint: disable=protected-access
  assert not [w for w in seen if "never awaited" in str(w.message)], [str(w.message) for w in seen]
