"""roboshape.data: RLDS round trips, clip batches, the collect stage (resume, determinism, refusals), validate, browse.

Most tests drive the collector with `FakePool` (synthetic episodes, scrambled completion order, scripted failures);
`test_real_workers_*` collect a tiny 32x32 dataset with the real simulator workers.
"""
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from configs import common
from conftest import _synthetic_episode
from roboshape import encoders
from roboshape.errors import UserError
from roboshape.data import browse
from roboshape.data import collect
from roboshape.data import dataset_path
from roboshape.data import reader
from roboshape.data import rlds
from roboshape.data import validate
from roboshape.envs import camera
from roboshape.envs import ids
from roboshape.envs import state as state_lib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TESTS = os.path.dirname(os.path.abspath(__file__))


class FakePool:
  """Stands in for roboshape.sim.SimPool: synthetic episodes, returned out of seed order; seeds % 4 == 1 fail."""

  def __init__(self, task="push", resolution=16, delay=0.0, failing=lambda s: s % 4 == 1):
    self.task, self.resolution, self.delay, self.failing = task, resolution, delay, failing
    self.requested = []

  def collect(self, seeds):
    seeds = list(seeds)
    self.requested += seeds
    order = seeds[1::2] + seeds[0::2]  # completion order differs from seed order
    for seed in order:
      time.sleep(self.delay)
      yield _synthetic_episode(seed, self.task, self.resolution, success=not self.failing(seed), state=True)


def _config(task="push", train=6, resolution=16, **overrides):
  config = common.get_config(task, "savi", "tiny")
  config.data.train_episodes = train
  config.env.resolution = resolution
  for key, value in overrides.items():
    section, field = key.split("__")
    config[section][field] = value
  return config


def _collect(config, path, pool=None):
  pool = pool or FakePool(config.task, config.env.resolution)
  return collect.collect_dataset(pool, path, collect.config_summary(config), collect.split_targets(config),
                                 progress=False)


def _state(path):
  with open(os.path.join(path, "roboshape.json")) as f:
    return json.load(f)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
  """A dataset collected in one go with FakePool: the config, its path and roboshape.json."""
  config = _config(train=6)
  path = str(tmp_path_factory.mktemp("reference") / "roboshape_push" / "1.0.0")
  _collect(config, path)
  return config, path, _state(path)


def test_round_trip_of_synthetic_episodes(synthetic_dataset):
  episodes = list(reader.read_episodes(synthetic_dataset, "train"))
  assert [e["seed"] for e in episodes] == [0, 1, 2, 3]
  for e in episodes:
    src = _synthetic_episode(e["seed"])
    num_steps = src["image"].shape[0]
    np.testing.assert_array_equal(e["image"], src["image"])
    np.testing.assert_array_equal(e["segmentation"], src["segmentation"])
    np.testing.assert_array_equal(e["action"][:-1], src["action"])
    np.testing.assert_array_equal(e["action"][-1], np.zeros(7, np.float32))
    np.testing.assert_array_equal(e["reward"][:-1], src["reward"])
    assert e["image"].dtype == np.uint8 and e["action"].dtype == np.float32
    assert e["is_last"].tolist() == [False] * (num_steps - 1) + [True]
    assert e["is_first"].tolist() == [True] + [False] * (num_steps - 1)
    assert e["is_terminal"][-1] and not e["is_terminal"][:-1].any()
    assert e["success"] and e["task"] == "push" and e["env_version"] == "synthetic-1"
  assert [e["seed"] for e in reader.read_episodes(synthetic_dataset, "val")] == [1_000_000, 1_000_001]


def test_the_dataset_identity_follows_the_shards_checksums_not_the_folder(synthetic_dataset, tmp_path):
  import roboshape.data as data_lib  # pylint: disable=import-outside-toplevel
  state = rlds.load_state(synthetic_dataset)
  first = data_lib.read_record(synthetic_dataset)
  assert first["identity"] == data_lib.identity(state) and len(first["identity"]) == 16
  assert (first["episodes"], first["complete"], first["name"]) == ({"train": 4, "val": 2}, True, "roboshape_push")
  # a copy of the dataset in another folder is the same dataset, and the run's record of it names no folder
  copy = str(shutil.copytree(synthetic_dataset, tmp_path / "elsewhere" / "roboshape_push" / "1.0.0"))
  assert data_lib.read_record(copy) == first
  path = collect.record_dataset(copy, str(tmp_path / "run"))
  assert path == os.path.join(str(tmp_path / "run"), "dataset.json")
  with open(path) as f:
    text = f.read()
  assert json.loads(text) == first and str(tmp_path) not in text and "elsewhere" not in text
  # a shard whose recorded checksum changes makes another dataset, and so does a shard less
  changed = json.loads(json.dumps(state))
  changed["splits"]["val"]["shards"][-1]["sha256"] = "0" * 64
  assert data_lib.identity(changed) != first["identity"]
  with open(os.path.join(copy, "roboshape.json"), "w") as f:
    json.dump(changed, f)
  assert data_lib.read_record(copy)["identity"] == data_lib.identity(changed)
  fewer = json.loads(json.dumps(state))
  fewer["splits"]["train"]["shards"].pop()
  assert len({data_lib.identity(fewer), data_lib.identity(changed), first["identity"]}) == 3
  assert data_lib.read_record(str(tmp_path / "absent")) is None


def test_depth_round_trips_and_comes_with_the_clips(tmp_path, synthetic_dataset):
  """A dataset collected with depth stores it (uint16 mm), reads it back, batches it with the clips, validates it."""
  def with_depth(seed):
    episode = _synthetic_episode(seed)
    episode["depth"] = (np.random.default_rng(seed).integers(300, 1500, episode["segmentation"].shape)
                        .astype(np.uint16))
    return episode

  path = rlds.write_dataset(str(tmp_path / "roboshape_push" / "1.0.0"),
                            {"train": [with_depth(s) for s in range(2)], "val": [with_depth(1_000_000)]})
  assert _state(path)["config"]["depth"] is True
  for e in reader.read_episodes(path, "train"):
    np.testing.assert_array_equal(e["depth"], with_depth(e["seed"])["depth"])
  b = next(reader.clip_batches(path, "train", clip_length=3, batch_size=4, seed=1))
  assert b["depth"].dtype == np.uint16 and b["depth"].shape == (4, 3, 16, 16)
  for i in range(4):
    s = int(b["start"][i])
    np.testing.assert_array_equal(b["depth"][i], with_depth(int(b["episode_seed"][i]))["depth"][s:s + 3])
  assert validate.main([path]) == 0
  with pytest.raises(ValueError, match="lacks depth"):
    rlds.write_dataset(str(tmp_path / "mixed"), {"train": [with_depth(0), _synthetic_episode(1)]})
  assert "depth" not in next(reader.read_episodes(synthetic_dataset, "val"))
  assert "depth" not in next(reader.clip_batches(synthetic_dataset, "train", clip_length=3, batch_size=2))
  # A dataset written before depth existed records no "depth": it matches a config without depth, not one with it.
  old = {k: v for k, v in _state(synthetic_dataset)["config"].items() if k != "depth"}
  wanted = dict(old, depth=False)
  assert collect.config_differences(old, wanted) == []
  assert collect.config_differences(old, dict(wanted, depth=True)) == ["depth: False in the dataset, True in the config"]


def test_clip_batches_are_deterministic_resumable_and_match_the_episodes(synthetic_dataset):
  batches = reader.clip_batches(synthetic_dataset, "train", clip_length=3, batch_size=5, seed=7)
  first = [next(batches) for _ in range(4)]
  again = reader.clip_batches(synthetic_dataset, "train", clip_length=3, batch_size=5, seed=7, start_batch=2)
  for want, got in zip(first[2:], [next(again), next(again)]):
    for key in ("video", "segmentation", "episode_seed", "start"):
      np.testing.assert_array_equal(want[key], got[key])
  other = next(reader.clip_batches(synthetic_dataset, "train", clip_length=3, batch_size=5, seed=8))
  assert not np.array_equal(other["video"], first[0]["video"])
  b = first[1]
  assert b["video"].shape == (5, 3, 16, 16, 3) and b["video"].dtype == np.uint8
  assert b["segmentation"].shape == (5, 3, 16, 16)
  for i in range(5):
    src = _synthetic_episode(int(b["episode_seed"][i]))
    s = int(b["start"][i])
    np.testing.assert_array_equal(b["video"][i], src["image"][s:s + 3])
    np.testing.assert_array_equal(b["segmentation"][i], src["segmentation"][s:s + 3])


def test_collect_keeps_the_first_successes_in_seed_order(reference):
  config, path, state = reference
  train = state["splits"]["train"]
  seeds = [s for shard in train["shards"] for s in shard["seeds"]]
  failed = [s for shard in train["shards"] for s in shard["failed_seeds"]]
  assert seeds == [0, 2, 3, 4, 6, 7] and failed == [1, 5]        # seeds % 4 == 1 fail and are replaced
  val = [s for shard in state["splits"]["val"]["shards"] for s in shard["seeds"]]
  assert val == [1_000_000] and collect.split_targets(config) == {"train": 6, "val": 1}
  assert state["complete"] and state["config"]["resolution"] == 16
  assert [e["seed"] for e in reader.read_episodes(path, "train")] == seeds


def test_same_config_gives_the_same_dataset_whatever_the_completion_order(reference, tmp_path):
  config, _, state = reference
  path = str(tmp_path / "roboshape_push" / "1.0.0")

  class ReversedPool(FakePool):
    def collect(self, seeds):
      for seed in reversed(list(seeds)):
        yield _synthetic_episode(seed, "push", 16, success=seed % 4 != 1, state=True)

  _collect(config, path, ReversedPool())
  def digests(st):
    return [s["sha256"] for split in st["splits"].values() for s in split["shards"]]

  assert digests(_state(path)) == digests(state)


def test_resume_after_sigkill_loses_and_duplicates_nothing(reference, tmp_path):
  config, _, ref_state = reference
  path = str(tmp_path / "roboshape_push" / "1.0.0")
  script = textwrap.dedent(f"""
      import sys; sys.path[:0] = [{ROOT!r}, {TESTS!r}]
      import test_data
      test_data._collect(test_data._config(train=6), {path!r}, test_data.FakePool(delay=0.2))
  """)
  state_file = os.path.join(path, "roboshape.json")
  proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
  deadline = time.time() + 60
  while time.time() < deadline and not (
      os.path.exists(state_file) and len(_state(path)["splits"]["train"]["shards"]) >= 2):
    time.sleep(0.02)
  time.sleep(0.13)  # somewhere inside the next episode or shard write
  os.kill(proc.pid, signal.SIGKILL)
  proc.wait()
  state = _state(path)
  killed_at = len(state["splits"]["train"]["shards"])
  assert 2 <= killed_at < 6 and not state["complete"]
  # What a kill between a shard's write and its record leaves behind: a temp file and an unrecorded shard.
  for name in (f"roboshape_push-train.tfrecord-{killed_at:05d}", f"roboshape_push-train.tfrecord-{killed_at:05d}.tmp"):
    with open(os.path.join(path, name), "wb") as f:
      f.write(b"garbage")
  pool = FakePool()
  _collect(config, path, pool)  # the same command again
  assert pool.requested[0] == state["splits"]["train"]["shards"][-1]["next_seed"]  # resumes after the last shard
  state = _state(path)
  assert state["complete"]
  for split in ("train", "val"):
    got = [(s["seeds"], s["failed_seeds"], s["sha256"]) for s in state["splits"][split]["shards"]]
    want = [(s["seeds"], s["failed_seeds"], s["sha256"]) for s in ref_state["splits"][split]["shards"]]
    assert got == want
  assert sorted(f for f in os.listdir(path) if ".tfrecord-" in f) == sorted(
      s["file"] for split in state["splits"].values() for s in split["shards"])
  assert [e["seed"] for e in reader.read_episodes(path, "train")] == [0, 2, 3, 4, 6, 7]


def test_disk_full_stops_with_a_clear_error_and_keeps_what_was_written(reference, tmp_path, monkeypatch):
  config, _, ref_state = reference
  path = str(tmp_path / "roboshape_push" / "1.0.0")
  real_write = rlds._write_records  # pylint: disable=protected-access
  calls = []

  def write_until_full(file, records):
    calls.append(file)
    if len(calls) == 3:
      with open(file, "wb") as f:
        f.write(b"partial")
      raise OSError(errno.ENOSPC, "No space left on device")
    real_write(file, records)

  monkeypatch.setattr(rlds, "_write_records", write_until_full)
  with pytest.raises(UserError, match="disk full.*2 train.*kept and readable"):
    _collect(config, path)
  assert not any(f.endswith(".tmp") for f in os.listdir(path))
  assert [e["seed"] for e in reader.read_episodes(path, "train", allow_incomplete=True)] == [0, 2]
  with pytest.raises(UserError, match="incomplete.*train 2/6"):
    reader.read_episodes(path, "train")
  monkeypatch.setattr(rlds, "_write_records", real_write)
  _collect(config, path)
  assert [s["sha256"] for s in _state(path)["splits"]["train"]["shards"]] == [
      s["sha256"] for s in ref_state["splits"]["train"]["shards"]]


def test_a_dataset_of_another_config_is_refused(reference, tmp_path):
  config, path, _ = reference
  workdir = str(tmp_path / "run")
  ref_root = os.path.dirname(os.path.dirname(path))
  shutil.copytree(ref_root, os.path.join(workdir, "data"))
  assert dataset_path(config, workdir) == os.path.join(workdir, "data", "roboshape_push", "1.0.0")
  other_res = _config(train=6, resolution=32)
  with pytest.raises(UserError, match=r"another config \(resolution: 16 in the dataset, 32 in the config\)"):
    collect.run(other_res, workdir)
  more_distractors = _config(train=6, env__max_distractors=6)
  with pytest.raises(UserError, match="max_distractors: 4 in the dataset, 6 in the config"):
    collect.run(more_distractors, workdir)
  with pytest.raises(UserError, match="task: 'push' in the dataset, 'pick' in the config"):
    collect.run(_config("pick", train=6), workdir)
  before = {f: os.path.getmtime(os.path.join(path, f)) for f in os.listdir(path)}
  assert _collect(config, path)["already_complete"]  # the same config: a complete dataset is left alone
  assert before == {f: os.path.getmtime(os.path.join(path, f)) for f in os.listdir(path)}


def test_validate_passes_a_good_dataset_and_names_corrupted_and_truncated_shards(reference, tmp_path, capsys):
  _, path, state = reference
  assert validate.main([path]) == 0
  assert "OK" in capsys.readouterr().out
  broken = str(tmp_path / "broken")
  shutil.copytree(path, broken)
  shards = state["splits"]["train"]["shards"]
  with open(os.path.join(broken, shards[1]["file"]), "r+b") as f:  # flip bytes inside a record
    f.seek(shards[1]["num_bytes"] // 2)
    f.write(b"\x00\xff\x00\xff")
  with open(os.path.join(broken, shards[3]["file"]), "r+b") as f:
    f.truncate(shards[3]["num_bytes"] - 100)
  assert validate.main([broken]) == 1
  err = capsys.readouterr().err
  assert f"shard {shards[1]['file']} is corrupted" in err
  assert f"shard {shards[3]['file']} is truncated" in err
  assert "cannot be decoded" in err


def test_validate_names_bad_episodes(tmp_path, capsys):
  bad_action = _synthetic_episode(0)
  bad_action["action"][2, 1] = 1.5
  blank = _synthetic_episode(1)
  blank["image"][4] = 0
  path = rlds.write_dataset(str(tmp_path / "d"), {"train": [bad_action, blank], "val": [_synthetic_episode(1)]})
  assert validate.main([path]) == 1
  err = capsys.readouterr().err
  assert "actions outside [-1, 1]" in err and "blank (constant) frame(s) at steps [4]" in err
  assert "seed 1 appears twice" in err


def test_a_wrist_camera_round_trips_validates_and_browses(tmp_path, synthetic_dataset):
  """env.cameras=("front", "wrist"): each episode stores the wrist view as observation/wrist_image and
  wrist_segmentation beside the front one, reads back, validates, and the browser shows both views."""
  def with_wrist(seed):
    episode = _synthetic_episode(seed)
    episode["wrist_image"] = episode["image"][:, ::-1].copy()
    episode["wrist_segmentation"] = episode["segmentation"][:, ::-1].copy()
    return episode

  path = rlds.write_dataset(str(tmp_path / "roboshape_push" / "1.0.0"),
                            {"train": [with_wrist(s) for s in range(2)], "val": [with_wrist(1_000_000)]})
  assert _state(path)["config"]["cameras"] == ["front", "wrist"]
  for e in reader.read_episodes(path, "train"):
    for key in ("image", "segmentation", "wrist_image", "wrist_segmentation"):
      np.testing.assert_array_equal(e[key], with_wrist(e["seed"])[key])
  assert validate.main([path]) == 0
  episode = with_wrist(0)
  frames = browse.frames_of(episode, scale=1)            # front image, its segmentation, wrist image, its segmentation
  assert frames.shape[1:] == (16, 4 * 16 + 3, 3)
  np.testing.assert_array_equal(frames[:, :, 2 * 17:2 * 17 + 16], episode["wrist_image"])
  with pytest.raises(ValueError, match="cameras"):
    rlds.write_dataset(str(tmp_path / "mixed"), {"train": [with_wrist(0), _synthetic_episode(1)]})
  # A dataset written before cameras existed has the front one alone: it matches a config with the front camera.
  old = {k: v for k, v in _state(synthetic_dataset)["config"].items() if k != "cameras"}
  front, both = _config("push"), _config("push", env__cameras=("front", "wrist"))
  assert collect.config_differences(old, dict(old, cameras=collect.config_summary(front)["cameras"])) == []
  assert collect.config_differences(old, dict(old, cameras=collect.config_summary(both)["cameras"])) == [
      "cameras: ['front'] in the dataset, ['front', 'wrist'] in the config"]
  # The complete two-camera dataset serves a front-only config (the same episodes' front frames); a config that
  # differs in anything else, or names a camera the dataset lacks, is still refused.
  stored = _state(path)["config"]
  assert collect.check_compatible(path, dict(stored, cameras=["front"]))["complete"]
  for other in (dict(stored, cameras=["front"], resolution=stored["resolution"] * 2),
                dict(stored, cameras=["front", "top"])):
    with pytest.raises(UserError, match="another config"):
      collect.check_compatible(path, other)
  assert not collect.serves_fewer_cameras(old, dict(old, cameras=["front", "wrist"]))
  # Pretraining clips of both views: each clip is the frames of one episode's front or wrist view, both views occur.
  batch = next(reader.clip_batches(path, "train", clip_length=3, batch_size=16, seed=0, cameras=("front", "wrist")))
  seen = set()
  for video, seg, seed, start in zip(batch["video"], batch["segmentation"], batch["episode_seed"], batch["start"]):
    e = with_wrist(int(seed))
    for view, (image, segmentation) in {"front": ("image", "segmentation"),
                                        "wrist": ("wrist_image", "wrist_segmentation")}.items():
      if np.array_equal(video, e[image][start:start + 3]):
        np.testing.assert_array_equal(seg, e[segmentation][start:start + 3])
        seen.add(view)
  assert seen == {"front", "wrist"}


def test_browse_writes_an_animation_and_a_strip(synthetic_dataset, tmp_path):
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  out = str(tmp_path / "ep.gif")
  assert browse.main([synthetic_dataset, "--split", "val", "--episode", "1", "--out", out, "--scale", "2"]) == 0
  gif = imageio.mimread(out)
  src = _synthetic_episode(1_000_001)
  assert len(gif) == src["image"].shape[0] and gif[0].shape[:2] == (32, 66)
  np.testing.assert_array_equal(np.asarray(gif[0])[::2, :32:2, :3], src["image"][0])
  strip = imageio.imread(str(tmp_path / "ep_strip.png"))
  assert strip.shape[0] == 32 and strip.shape[1] > 66
  assert browse.main([synthetic_dataset, "--episode", "9", "--out", out]) == 2


# ----------------------------------------------------------------------------------------- real simulator workers
@pytest.fixture(scope="module")
def sim_pool():
  """One real simulator worker (push, 32x32, with depth, the front and the wrist camera), shared by the tests below."""
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel
  with SimPool(EnvSpec("push", resolution=32, depth=True, cameras=("front", "wrist")), num_workers=1) as pool:
    yield pool


@pytest.fixture(scope="module")
def real_dataset(sim_pool, tmp_path_factory):
  """The collect stage (`collect.run`) on the real worker: 2 train + 1 val episodes at 32x32 with depth; its path."""
  import roboshape.sim  # pylint: disable=import-outside-toplevel
  config = _config("push", train=2, resolution=32, env__depth=True, env__cameras=("front", "wrist"))
  workdir = str(tmp_path_factory.mktemp("real_run"))
  specs = []

  def borrowed_pool(spec, num_workers):  # the stage's SimPool is the shared one (one simulator start-up)
    specs.append((spec, num_workers))
    return _Borrowed(sim_pool)

  with pytest.MonkeyPatch.context() as mp:
    mp.setattr(roboshape.sim, "SimPool", borrowed_pool)
    collect.run(config, workdir)
  assert specs == [(sim_pool.spec, 0)]
  return dataset_path(config, workdir)


class _Borrowed:
  def __init__(self, pool):
    self.pool = pool

  def __enter__(self):
    return self.pool

  def __exit__(self, *exc):
    pass


def test_real_workers_dataset_reads_with_plain_tfds_and_validates(real_dataset):
  script = textwrap.dedent(f"""
      import json, sys
      import tensorflow_datasets as tfds
      builder = tfds.builder_from_directory({real_dataset!r})
      out = {{}}
      for split in ("train", "val"):
        for ep in builder.as_dataset(split=split):
          steps = list(ep["steps"])
          meta = ep["episode_metadata"]
          out.setdefault(split, []).append(dict(
              seed=int(meta["seed"]), success=bool(meta["success"]), task=meta["task"].numpy().decode(),
              env_version=meta["env_version"].numpy().decode(), steps=len(steps),
              image=[steps[0]["observation"]["image"].dtype.name,
                     steps[0]["observation"]["image"].shape.as_list()],
              seg=steps[0]["observation"]["segmentation"].shape.as_list(),
              depth=[steps[0]["observation"]["depth"].dtype.name,
                     steps[0]["observation"]["depth"].shape.as_list()],
              wrist=[[steps[0]["observation"][k].dtype.name, steps[0]["observation"][k].shape.as_list()]
                     for k in ("wrist_image", "wrist_segmentation", "wrist_depth")],
              hand_in_wrist=sum(bool((s["observation"]["wrist_segmentation"].numpy() == 13).any()) for s in steps)
                            / len(steps),
              state=[steps[0]["observation"]["state"].dtype.name,
                     steps[0]["observation"]["state"].shape.as_list()],
              first=[bool(s["is_first"]) for s in steps].index(True), last=bool(steps[-1]["is_last"]),
              amax=max(float(abs(s["action"].numpy()).max()) for s in steps)))
      assert not any(m.startswith("roboshape") for m in sys.modules)
      print(json.dumps(out))
  """)
  out = subprocess.run([sys.executable, "-c", script], cwd="/", capture_output=True, text=True, timeout=120,
                       check=False, env={**os.environ, "PYTHONPATH": ""})
  assert out.returncode == 0, out.stderr[-2000:]
  got = json.loads(out.stdout.strip().splitlines()[-1])
  state = _state(real_dataset)
  for split in ("train", "val"):
    seeds = [s for shard in state["splits"][split]["shards"] for s in shard["seeds"]]
    assert [e["seed"] for e in got[split]] == seeds
    assert sum(e["steps"] for e in got[split]) == sum(s["num_steps"] for s in state["splits"][split]["shards"])
  assert len(got["train"]) == 2 and len(got["val"]) == 1 and got["val"][0]["seed"] >= 1_000_000
  for e in got["train"] + got["val"]:
    assert e["success"] and e["task"] == "push" and e["env_version"].startswith("roboshape-envs")
    assert e["image"] == ["uint8", [32, 32, 3]] and e["seg"] == [32, 32] and e["depth"] == ["uint16", [32, 32]]
    assert e["state"] == ["float32", [65]]
    assert e["wrist"] == [["uint8", [32, 32, 3]], ["uint8", [32, 32]], ["uint16", [32, 32]]]
    assert e["hand_in_wrist"] > 0.9          # the wrist camera sees the fingers (id 13) in (nearly) every frame
    assert e["first"] == 0 and e["last"] and 0 < e["amax"] <= 1
  assert validate.main([real_dataset]) == 0


def test_real_workers_give_the_same_episode_for_the_same_seed(real_dataset, sim_pool):
  stored = next(reader.read_episodes(real_dataset, "train"))
  (again,) = list(sim_pool.collect([stored["seed"]]))
  np.testing.assert_array_equal(stored["image"], again["image"])
  np.testing.assert_array_equal(stored["segmentation"], again["segmentation"])
  np.testing.assert_array_equal(stored["wrist_image"], again["wrist_image"])
  np.testing.assert_array_equal(stored["depth"], again["depth"])
  np.testing.assert_array_equal(stored["state"], again["state"])
  # The state token a policy is trained on (from the dataset) is the one closed-loop control computes (from a worker).
  enc = encoders.get("state").build(None, "")
  obs = sim_pool.reset([stored["seed"]])
  np.testing.assert_array_equal(np.asarray(enc.encode_episode({"state": stored["state"]}))[0],
                                np.asarray(enc.encode_batch({"state": obs["state"][:, None]}))[0, 0])
  np.testing.assert_array_equal(obs["depth"][0], stored["depth"][0])
  objects = encoders.get("objects").build(common.get_config("push", "objects", "small"), "")
  assert objects.inputs == ("image", "segmentation", "depth")
  np.testing.assert_allclose(   # the same frame; batch shapes may change float sums in the last bits
      np.asarray(objects.encode_episode({k: stored[k] for k in objects.inputs}))[0],
      np.asarray(objects.encode_batch({k: obs[k][:, None] for k in objects.inputs}))[0, 0], rtol=0, atol=1e-6)
  cuts = state_lib.slices()
  first = stored["state"][0]
  assert first[cuts["cube_pos"]][2] == pytest.approx(0.02, abs=2e-3)    # the cube rests on the table
  present = first[cuts["distractors"]].reshape(-1, 5)[:, 4]
  visible = {i for i in np.unique(stored["segmentation"]) if 5 <= i < ids.HAND}   # distractors (13: the hand)
  assert present.sum() >= len(visible) >= 1 and set(np.flatnonzero(present) + 5) >= visible
  np.testing.assert_array_equal(stored["action"][:-1], again["action"])
  np.testing.assert_array_equal(stored["reward"][:-1], again["reward"])
  assert set(np.unique(stored["segmentation"])) >= {1, 2, 3}  # table, robot and cube are in view
  seg, depth = stored["segmentation"][0], stored["depth"][0].astype(np.int64)
  # The camera looks down at the table: the backdrop behind it is farther, the cube on it nearer than its far edge.
  assert np.median(depth[seg == 0]) > np.median(depth[seg == 1]) > 0
  assert depth[seg == 3].max() < depth[seg == 1].max() and 100 < depth.min() and depth.max() < 5000


def test_the_closed_loop_sees_every_view_as_collected_and_the_wrist_cells_tokens_match(real_dataset, sim_pool):
  """Replaying a stored episode's actions in the worker gives every camera's frames and the state, step by step, bit
  for bit; and the run encoder of a two-camera objects cell with proprioception and `+rel` (the views, the
  proprioception token, each front token's object relative to the hand) makes the same tokens of the live frames as
  of the stored ones."""
  stored = next(reader.read_episodes(real_dataset, "train"))
  frames = [sim_pool.reset([stored["seed"]])]
  for action in stored["action"][:-1]:                      # the last action is the episode's padding
    frames.append(sim_pool.step(action[None]))
  assert frames[-1]["success"][0]
  for key in camera.all_keys(("front", "wrist")) + ("state",):
    np.testing.assert_array_equal(np.stack([f[key][0] for f in frames]), stored[key], err_msg=key)
  config = common.get_config("push", "objects", "small")
  config.env.cameras, config.policy.proprio, config.policy.hand_relative = ("front", "wrist"), True, True
  run_encoder = encoders.build_encoder(config, "")
  assert set(run_encoder.inputs) >= {"wrist_image", "wrist_segmentation", "wrist_depth", "state"}
  live = {k: np.stack([f[k][0] for f in frames])[None] for k in run_encoder.inputs}
  tokens = np.asarray(run_encoder.encode_episode({k: stored[k] for k in run_encoder.inputs}))
  assert np.abs(tokens).sum() > 0
  np.testing.assert_allclose(tokens, np.asarray(run_encoder.encode_batch(live))[0], rtol=0, atol=1e-6)


def test_a_wrist_grid_runs_every_stage_on_the_two_camera_dataset(real_dataset, sim_pool, tmp_path):
  """configs/reproduce.py:tiny with the column savi+wrist: collect (the dataset the collect stage wrote above, found
  complete in the grid's push_wrist folder), pretrain (one SAVi on clips of both views), cache, train_policy,
  evaluate (in the real worker, which renders both cameras) and report."""
  import roboshape.sim  # pylint: disable=import-outside-toplevel
  from configs import reproduce  # pylint: disable=import-outside-toplevel
  from conftest import cheap_compiles  # pylint: disable=import-outside-toplevel
  from roboshape import rundir, stages  # pylint: disable=import-outside-toplevel
  config = reproduce.get_config("tiny")
  config.grid.tasks, config.grid.encoders = ("push",), ("savi+wrist",)
  config.data.train_episodes, config.env.resolution, config.env.depth = 2, 32, True    # the real dataset's
  config.eval.levels, config.eval.rollouts_per_seed, config.eval.videos_per_level = ("train",), 1, 1
  workdir = str(tmp_path / "grid")
  data = rundir.grid_data_dir(config, workdir, "push", ("wrist",))
  assert data.endswith("push_wrist")
  shutil.copytree(os.path.dirname(real_dataset), os.path.join(data, os.path.basename(os.path.dirname(real_dataset))))
  specs = []

  def borrowed_pool(spec, num_workers):
    specs.append(spec.cameras)
    return _Borrowed(sim_pool)

  with pytest.MonkeyPatch.context() as mp, cheap_compiles():
    mp.setattr(roboshape.sim, "SimPool", borrowed_pool)
    stages.run(config, workdir)
  assert specs and set(specs) == {("front", "wrist")}
  run = rundir.grid_run_dir(workdir, "push", "savi+wrist")
  with open(os.path.join(run, "config.json")) as f:
    assert json.load(f)["env"]["cameras"] == ["front", "wrist"]
  with open(os.path.join(rundir.eval_dir(run), rundir.RESULTS_FILE)) as f:
    assert json.load(f)
  figures = sorted(os.listdir(os.path.join(run, "savi", "figures")))
  assert figures[-2:] == ["step_0000020.png", "step_0000020_wrist.png"]   # the last validation draws both views
  with open(os.path.join(run, "savi", "val_metrics.json")) as f:
    last = json.load(f)[-1]
  assert {"cube_found_front", "cube_found_wrist", "fg_ari_front", "fg_ari_wrist"} <= set(last)   # and scores each
  (features,) = os.listdir(os.path.join(run, "features"))
  with open(os.path.join(run, "features", features, "manifest.json")) as f:
    assert json.load(f)["num_tokens"] == 2 * config.savi.num_slots       # each view's slots
  import imageio.v2 as imageio  # pylint: disable=import-outside-toplevel
  (gif,) = [n for n in os.listdir(rundir.videos_dir(run)) if n.endswith(".gif")]
  frame = imageio.mimread(os.path.join(rundir.videos_dir(run), gif))[0]
  assert frame.shape[:2] == (4 * 32, 4 * (32 + 2 + 32) + 8)     # both views side by side, x4, padded to 16s
  report = open(os.path.join(workdir, "report", "report.md")).read()
  assert "SAVi+wrist" in report and "`+wrist`: a second camera on the hand" in report


def test_a_tfds_dataset_roboshape_did_not_write_is_refused_and_left_as_it_is(reference, tmp_path):
  config, path, _ = reference
  foreign = str(tmp_path / "data" / "roboshape_push" / "1.0.0")
  shutil.copytree(path, foreign)
  os.remove(os.path.join(foreign, "roboshape.json"))        # TFDS metadata and records, but no roboshape.json
  before = {f: open(os.path.join(foreign, f), "rb").read() for f in os.listdir(foreign) if f != ".collect.lock"}
  with pytest.raises(UserError, match=r"holds a TFDS dataset that roboshape did not write .* left as it is") as e:
    _collect(config, foreign)
  assert "\n" not in str(e.value)
  after = {f: open(os.path.join(foreign, f), "rb").read() for f in os.listdir(foreign) if f != ".collect.lock"}
  assert after == before


def test_a_new_dataset_records_itself_before_any_tfds_metadata(tmp_path):
  config = _config(train=6)
  path = str(tmp_path / "roboshape_push" / "1.0.0")
  rlds.DatasetWriter(path, collect.config_summary(config), collect.split_targets(config))
  assert os.listdir(path) == ["roboshape.json"] and not _state(path)["complete"]
  assert _collect(config, path)["complete"]                 # and a collection goes on from there
