"""The RLDS layout of the RoboShape dataset and a writer that commits it shard by shard.

A dataset is one TFDS directory (see `roboshape.data.dataset_path`) that plain TFDS reads:

  tfds.builder_from_directory(path).as_dataset(split="train")     # splits "train" and "val"

Each example is one episode (RLDS): `steps` with S = T + 1 steps and `episode_metadata`.
  steps/observation/image         uint8 [H, W, 3]  the camera frame before the step's action (PNG in the shards)
  steps/observation/segmentation  uint8 [H, W]     simulator object ids (0 floor, 1 table, 2 robot, 3 red cube,
                                                   4 target/bin, 5+i distractor i)
  steps/observation/depth         uint16 [H, W]    camera depth in millimetres (only in datasets collected with
                                                   env.depth=True; roboshape.json's config says "depth": true)
  steps/observation/wrist_image, wrist_segmentation, (wrist_depth)
                                                   the wrist camera's frames, as the front camera's above (only in
                                                   datasets collected with env.cameras naming it; roboshape.json's
                                                   config lists the cameras; roboshape/envs/camera.py names them)
  steps/observation/state         float32 [65]     the privileged simulator state (roboshape/envs/state.py: tcp pose,
                                                   gripper, arm joints, cube pose, goal, distractors); in datasets
                                                   of roboshape.json "state": true (all collected since it exists)
  steps/action                    float32 [7]      the action the env executed; zeros on the last step
  steps/reward                    float32          reward of the step's action; 0 on the last step
  steps/discount                  float32          1
  steps/is_first, is_last         bool             first / last step of the episode
  steps/is_terminal               bool             last step of an episode that ended by success
  episode_metadata                task, level, seed, success, env_version

Writing: `DatasetWriter` writes each shard to a temporary file and renames it into place, then records it (seeds,
step count, size, sha256) in roboshape.json and rewrites the TFDS metadata (dataset_info.json, features.json), each
file replaced atomically. So at any moment the directory is a readable dataset of the shards committed so far,
roboshape.json says whether it is complete, and a killed writer loses at most the shard it was writing.
`write_dataset` writes whole splits at once (tests, tools) without any simulator. `shard_problems` finds the shards
whose file is missing or differs from its record, and `rewrite_shard` puts one back from its episodes when the new
file is byte for byte the recorded one (the collect stage re-collects damaged shards this way).
"""
import copy
import errno
import hashlib
import json
import os
import shutil
from typing import Any, Dict, List, Mapping, Optional, Sequence

import numpy as np
import tensorflow as tf
import tensorflow_datasets as tfds
from tensorflow_datasets.core import example_serializer

from roboshape import data as data_lib
from roboshape import fileio
from roboshape.errors import UserError
from roboshape.envs import camera
from roboshape.envs import state as state_lib

LAYOUT = "roboshape-rlds-1"
FILENAME_TEMPLATE = "{DATASET}-{SPLIT}.{FILEFORMAT}-{SHARD_INDEX}"
ACTION_DIM = 7
DESCRIPTION = (
    "RoboShape expert demonstrations (Franka Panda, ManiSkill3) in the RLDS layout: one example per episode with "
    "`steps` (observation/image uint8 HxWx3, observation/segmentation uint8 HxW object ids, with env.depth also "
    "observation/depth uint16 HxW millimetres, with env.cameras naming the wrist camera also its "
    "observation/wrist_image, wrist_segmentation (and wrist_depth), observation/state float32[65] the privileged simulator state, "
    "action float32[7] as executed, reward, discount, is_first, is_last, is_terminal) and `episode_metadata` (task, level, seed, success, "
    "env_version). The last step of an episode holds the final observation and a zero action. Only successful "
    "expert episodes are stored; metadata.json holds the collection config.")


def features(resolution: int, depth: bool = False, state: bool = False,
             cameras: Sequence[str] = camera.DEFAULT) -> tfds.features.FeaturesDict:
  """The TFDS features of an episode at `resolution` x `resolution` pixels: each camera's image and segmentation
  (and depth if `depth`) under its keys (roboshape/envs/camera.py), observation/state if `state`."""
  scalar = tfds.features.Scalar
  observation = {}
  for name in cameras:
    image, segmentation, depth_key = camera.keys(name)
    observation[image] = tfds.features.Image(shape=(resolution, resolution, 3), dtype=np.uint8,
                                             encoding_format="png")
    observation[segmentation] = tfds.features.Tensor(shape=(resolution, resolution), dtype=np.uint8,
                                                     encoding=tfds.features.Encoding.ZLIB)
    if depth:
      observation[depth_key] = tfds.features.Tensor(shape=(resolution, resolution), dtype=np.uint16,
                                                    encoding=tfds.features.Encoding.ZLIB)
  if state:
    observation["state"] = tfds.features.Tensor(shape=(state_lib.DIM,), dtype=np.float32,
                                                doc=state_lib.describe())
  return tfds.features.FeaturesDict({
      "steps": tfds.features.Dataset({
          "observation": tfds.features.FeaturesDict(observation),
          "action": tfds.features.Tensor(shape=(ACTION_DIM,), dtype=np.float32),
          "reward": scalar(dtype=np.float32),
          "discount": scalar(dtype=np.float32),
          "is_first": scalar(dtype=np.bool_),
          "is_last": scalar(dtype=np.bool_),
          "is_terminal": scalar(dtype=np.bool_),
      }),
      "episode_metadata": tfds.features.FeaturesDict({
          "task": tfds.features.Text(),
          "level": tfds.features.Text(),
          "seed": scalar(dtype=np.int64),
          "success": scalar(dtype=np.bool_),
          "env_version": tfds.features.Text(),
      }),
  })


def features_of(summary: Mapping[str, Any]) -> tfds.features.FeaturesDict:
  """The features of the dataset roboshape.json's config `summary` describes (resolution, depth, state, cameras)."""
  return features(int(summary["resolution"]), bool(summary.get("depth", False)), bool(summary.get("state", False)),
                  tuple(summary.get("cameras", camera.DEFAULT)))


def to_rlds(episode: Mapping[str, Any]) -> Dict[str, Any]:
  """A simulator episode (image [T+1,H,W,3], segmentation [T+1,H,W], action [T,7], reward [T], ...) -> RLDS example.

  The RLDS episode has S = T + 1 steps: step t holds observation t and action t; the last step holds the final
  observation, a zero action and reward, and is_last (and is_terminal when the episode ended by success).
  """
  image = np.asarray(episode["image"], np.uint8)
  segmentation = np.asarray(episode["segmentation"], np.uint8)
  action = np.asarray(episode["action"], np.float32).reshape(-1, ACTION_DIM)
  reward = np.asarray(episode["reward"], np.float32).reshape(-1)
  num_steps = image.shape[0]
  if segmentation.shape != image.shape[:3] or action.shape[0] != num_steps - 1 or reward.shape[0] != num_steps - 1:
    raise ValueError(f"episode of seed {episode.get('seed')}: inconsistent shapes image {image.shape}, "
                     f"segmentation {segmentation.shape}, action {action.shape}, reward {reward.shape}")
  observation = {}
  for name in camera.CAMERAS:
    keys = camera.keys(name)
    if keys[0] not in episode:
      continue
    for key, dtype in zip(keys, (np.uint8, np.uint8, np.uint16)):
      if key in episode:
        observation[key] = np.asarray(episode[key], dtype)
        if observation[key].shape[:3] != image.shape[:3]:
          raise ValueError(f"episode of seed {episode.get('seed')}: {key} {observation[key].shape}, "
                           f"image {image.shape}")
  if "state" in episode:
    observation["state"] = np.asarray(episode["state"], np.float32)
    if observation["state"].shape != (num_steps, state_lib.DIM):
      raise ValueError(f"episode of seed {episode.get('seed')}: state {observation['state'].shape}, "
                       f"want [{num_steps}, {state_lib.DIM}]")
  index = np.arange(num_steps)
  is_last = index == num_steps - 1
  return {
      "steps": {
          "observation": observation,
          "action": np.concatenate([action, np.zeros((1, ACTION_DIM), np.float32)]),
          "reward": np.concatenate([reward, np.zeros((1,), np.float32)]),
          "discount": np.ones((num_steps,), np.float32),
          "is_first": index == 0,
          "is_last": is_last,
          "is_terminal": is_last & bool(episode.get("terminated", episode["success"])),
      },
      "episode_metadata": {
          "task": str(episode["task"]),
          "level": str(episode["level"]),
          "seed": int(episode["seed"]),
          "success": bool(episode["success"]),
          "env_version": str(episode["env_version"]),
      },
  }


def episodes_per_shard(num_episodes: int) -> int:
  """Shard size of a split of `num_episodes`: about 20 shards, at most 20 episodes each (a few MB at 64x64)."""
  return max(1, min(20, num_episodes // 20))


def shard_filename(task: str, split: str, index: int) -> str:
  return f"{data_lib.dataset_name(task)}-{split}.tfrecord-{index:05d}"


def file_sha256(path: str) -> str:
  digest = hashlib.sha256()
  with open(path, "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
      digest.update(block)
  return digest.hexdigest()


def _write_records(path: str, records: Sequence[bytes]) -> None:
  """Writes a TFRecord file; a full disk raises OSError(ENOSPC) whatever layer noticed it."""
  try:
    with tf.io.TFRecordWriter(path) as writer:
      for record in records:
        writer.write(record)
    with open(path, "rb+") as f:
      os.fsync(f.fileno())
  except (tf.errors.OpError, OSError) as e:
    if fileio.disk_full(e):
      raise OSError(errno.ENOSPC, fileio.NO_SPACE, path) from e
    raise


def load_state(path: str) -> Optional[Dict[str, Any]]:
  """roboshape.json of the dataset at `path` (roboshape.data.read_state), or None when there is none; a UserError
  for another layout than this roboshape's."""
  state = data_lib.read_state(path)
  if state is None:
    return None
  if state.get("layout") != LAYOUT:
    raise UserError(f"{path} holds a dataset of layout {state.get('layout')!r}, this roboshape writes {LAYOUT!r}: "
                    "collect it again into another directory.")
  return state


def shard_problems(path: str, state: Mapping[str, Any], splits: Optional[Sequence[str]] = None,
                   hashes: bool = True) -> List[Dict[str, Any]]:
  """The recorded shards of the dataset at `path` whose file is missing, or differs from roboshape.json's record.

  Args:
    path: the dataset directory.
    state: its roboshape.json (`load_state`).
    splits: the splits to check (default: all).
    hashes: also compare the sha256 of every shard whose size matches (a fraction of a second for a :small dataset).
  Returns:
    [{"split", "index", "file", "problem"}], problem e.g. "missing" or "truncated or changed (10 bytes, 20
    recorded)", in split and shard order.
  """
  found = []
  for split, info in state["splits"].items():
    if splits is not None and split not in splits:
      continue
    for index, shard in enumerate(info["shards"]):
      problem = _shard_problem(os.path.join(path, shard["file"]), shard, hashes)
      if problem:
        found.append({"split": split, "index": index, "file": shard["file"], "problem": problem})
  return found


def _shard_problem(file: str, shard: Mapping[str, Any], hashes: bool) -> str:
  """What is wrong with one shard file against its record ("" when nothing is)."""
  if not os.path.isfile(file):
    return "missing"
  size = os.path.getsize(file)
  if size != shard["num_bytes"]:
    return f"truncated or changed ({size} bytes, {shard['num_bytes']} recorded)"
  if hashes and file_sha256(file) != shard["sha256"]:
    return "corrupted (its sha256 differs from the recorded one)"
  return ""


def rewrite_shard(path: str, state: Mapping[str, Any], split: str, index: int,
                  episodes: Sequence[Mapping[str, Any]]) -> None:
  """Writes shard `index` of `split` again from its `episodes` (the recorded seeds, in order), in place.

  The new file replaces the old one (atomically) only when its size and sha256 are those roboshape.json records,
  so a repaired dataset is byte for byte the one collected; otherwise nothing changes and a UserError says to
  collect again.
  """
  shard = state["splits"][split]["shards"][index]
  seeds = [int(e["seed"]) for e in episodes]
  if seeds != shard["seeds"]:
    raise ValueError(f"shard {shard['file']} records seeds {shard['seeds']}, got episodes of seeds {seeds}")
  config = state["config"]
  serialize = EpisodeSerializer(features_of(config))
  final = os.path.join(path, shard["file"])
  tmp = final + ".tmp"
  try:
    _write_records(tmp, [serialize(e) for e in episodes])
    same = os.path.getsize(tmp) == shard["num_bytes"] and file_sha256(tmp) == shard["sha256"]
    if same:
      os.replace(tmp, final)
  finally:
    if os.path.exists(tmp):
      os.remove(tmp)
  if not same:
    raise UserError(f"re-collecting the damaged shard {final} gave other bytes than recorded (the simulator "
                    "differs from the one that collected it): repair it with the roboshape that collected it, or "
                    f"collect a new dataset into another --config.data.dir. {path} is left as it is.")


class EpisodeSerializer:
  """Simulator episodes -> tf.train.Example bytes of `feats`, identical from run to run (deterministic map order)."""

  def __init__(self, feats: tfds.features.FeaturesDict):
    self.features = feats
    self._serializer = example_serializer.ExampleSerializer(feats.get_serialized_info())

  def __call__(self, episode: Mapping[str, Any]) -> bytes:
    example = self._serializer.get_tf_example(self.features.encode_example(to_rlds(episode)))
    return example.SerializeToString(deterministic=True)


class DatasetWriter:
  """Writes one RoboShape dataset shard by shard, resumable: what is committed stays, and is readable at once.

  Usage:
    writer = DatasetWriter(path, config_summary, {"train": 200, "val": 10}, seed_bases={"train": 0, "val": 10**6})
    writer.add_shard("train", episodes, failed_seeds=[...], next_seed=...)   # repeatedly, in seed order
    writer.finish()
  """

  def __init__(self, path: str, config_summary: Mapping[str, Any], targets: Mapping[str, int],
               seed_bases: Optional[Mapping[str, int]] = None):
    self.path = path
    state = load_state(path)
    fresh = state is None
    if fresh:
      seed_bases = seed_bases or {split: 0 for split in targets}
      state = {
          "layout": LAYOUT,
          "name": data_lib.dataset_name(config_summary["task"]),
          "config": dict(config_summary),
          "env_version": None,
          "complete": False,
          "splits": {split: {"target": int(n), "seed_base": int(seed_bases[split]),
                             "episodes_per_shard": episodes_per_shard(int(n)), "shards": []}
                     for split, n in targets.items()},
      }
    elif state["complete"]:
      raise UserError(f"{path} already holds a complete dataset, which is never rewritten: give another path to "
                      "collect a new one.")
    self.state = state
    self.resolution = int(state["config"]["resolution"])
    self.depth = bool(state["config"].get("depth", False))
    self.has_state = bool(state["config"].get("state", False))
    self.cameras = tuple(state["config"].get("cameras", camera.DEFAULT))
    self.features = features_of(state["config"])
    self._serialize = EpisodeSerializer(self.features)
    os.makedirs(path, exist_ok=True)
    if fresh:   # roboshape.json before any TFDS metadata: metadata without it is not roboshape's (collect.py)
      fileio.atomic_write_text(os.path.join(self.path, data_lib.STATE_FILE), json.dumps(state, indent=1))
    self._remove_stale_files()

  @property
  def task(self) -> str:
    return self.state["config"]["task"]

  def shards(self, split: str) -> List[Dict[str, Any]]:
    return self.state["splits"][split]["shards"]

  def num_episodes(self, split: str) -> int:
    return sum(len(s["seeds"]) for s in self.shards(split))

  def _remove_stale_files(self) -> None:
    """Deletes temporary files and shards that a killed writer left but never recorded."""
    recorded = {s["file"] for split in self.state["splits"].values() for s in split["shards"]}
    prefix = data_lib.dataset_name(self.task) + "-"
    for name in os.listdir(self.path):
      stale_shard = name.startswith(prefix) and ".tfrecord-" in name and name not in recorded
      if name.endswith(".tmp") or stale_shard:
        os.remove(os.path.join(self.path, name))

  def add_shard(self, split: str, episodes: Sequence[Mapping[str, Any]], failed_seeds: Sequence[int] = (),
                next_seed: Optional[int] = None) -> Dict[str, Any]:
    """Commits one shard of successful `episodes` (simulator dicts), in order; returns its record.

    failed_seeds: the seeds whose expert failed since the previous shard (recorded, not stored).
    next_seed: the first seed not yet resolved after this shard (where a resumed collection starts).
    Raises OSError(ENOSPC) on a full disk, leaving the dataset as it was before the call.
    """
    if not episodes:
      raise ValueError("a shard needs at least one episode")
    env_versions = {str(e["env_version"]) for e in episodes}
    known = self.state["env_version"]
    if len(env_versions) > 1 or (known is not None and env_versions != {known}):
      raise UserError(f"the simulator's env version changed ({known or ''} vs {', '.join(sorted(env_versions))}) "
                      f"while collecting {self.path}: finish it with the roboshape that began it, or collect a new "
                      "dataset into another --config.data.dir.")
    for e in episodes:
      if e["task"] != self.task or e["image"].shape[1:] != (self.resolution, self.resolution, 3):
        raise ValueError(f"episode of seed {e['seed']} ({e['task']}, {e['image'].shape}) does not belong in "
                         f"a {self.task} dataset at resolution {self.resolution}")
      if ("depth" in e) != self.depth:
        raise ValueError(f"episode of seed {e['seed']} {'has' if 'depth' in e else 'lacks'} depth, the dataset "
                         f"{'stores' if self.depth else 'does not store'} it")
      stored = camera.stored(e)
      if stored != self.cameras:
        raise ValueError(f"episode of seed {e['seed']} has the cameras {stored}, the dataset stores {self.cameras}")
      if ("state" in e) != self.has_state:
        raise ValueError(f"episode of seed {e['seed']} {'has' if 'state' in e else 'lacks'} a state, the dataset "
                         f"{'stores' if self.has_state else 'does not store'} it")
    index = len(self.shards(split))
    name = shard_filename(self.task, split, index)
    final = os.path.join(self.path, name)
    tmp = final + ".tmp"
    records = [self._serialize(e) for e in episodes]
    try:
      _write_records(tmp, records)
      os.replace(tmp, final)
    except BaseException:
      if os.path.exists(tmp):
        os.remove(tmp)
      raise
    record = {
        "file": name,
        "seeds": [int(e["seed"]) for e in episodes],
        "failed_seeds": [int(s) for s in failed_seeds],
        "next_seed": int(next_seed if next_seed is not None else max(int(e["seed"]) for e in episodes) + 1),
        "num_steps": int(sum(e["image"].shape[0] for e in episodes)),
        "num_bytes": os.path.getsize(final),
        "sha256": file_sha256(final),
    }
    new_state = copy.deepcopy(self.state)
    new_state["env_version"] = env_versions.pop()
    new_state["splits"][split]["shards"].append(record)
    try:
      self._save(new_state)
    except BaseException:
      os.remove(final)  # not recorded: the dataset stays as it was (its metadata too, best effort)
      try:
        write_tfds_metadata(self.path, self.state, self.features)
      except Exception:  # pylint: disable=broad-except
        pass
      raise
    self.state = new_state
    return record

  def finish(self) -> None:
    """Marks the dataset complete (after checking every split reached its target)."""
    for split, info in self.state["splits"].items():
      have = self.num_episodes(split)
      if have != info["target"]:
        raise ValueError(f"split {split} has {have} episodes, {info['target']} wanted")
    new_state = copy.deepcopy(self.state)
    new_state["complete"] = True
    self._save(new_state)
    self.state = new_state

  def _save(self, state: Dict[str, Any]) -> None:
    """Writes the TFDS metadata for `state`, then roboshape.json (each file replaced atomically)."""
    write_tfds_metadata(self.path, state, self.features)
    fileio.atomic_write_text(os.path.join(self.path, data_lib.STATE_FILE), json.dumps(state, indent=1))


def write_tfds_metadata(path: str, state: Mapping[str, Any], feats: tfds.features.FeaturesDict) -> None:
  """dataset_info.json, features.json and metadata.json describing the shards recorded in `state`."""
  name = state["name"]
  identity = tfds.core.DatasetIdentity(name=name, version=tfds.core.Version(data_lib.VERSION),
                                       data_dir=path, module_name="")
  metadata = tfds.core.MetadataDict(config=dict(state["config"]), env_version=state["env_version"],
                                    complete=bool(state["complete"]),
                                    seeds={k: [s for shard in v["shards"] for s in shard["seeds"]]
                                           for k, v in state["splits"].items()})
  info = tfds.core.DatasetInfo(builder=identity, features=feats, description=DESCRIPTION, metadata=metadata)
  info.set_file_format("tfrecord")
  splits = []
  for split, split_state in state["splits"].items():
    if not split_state["shards"]:
      continue
    template = tfds.core.ShardedFileTemplate(data_dir=path, template=FILENAME_TEMPLATE, dataset_name=name,
                                             split=split, filetype_suffix="tfrecord")
    splits.append(tfds.core.SplitInfo(name=split, shard_lengths=[len(s["seeds"]) for s in split_state["shards"]],
                                      num_bytes=sum(s["num_bytes"] for s in split_state["shards"]),
                                      filename_template=template))
  info.set_splits(tfds.core.SplitDict(splits))
  staging = os.path.join(path, ".metadata.tmp")
  shutil.rmtree(staging, ignore_errors=True)
  os.makedirs(staging)
  try:
    info.write_to_directory(staging)
    for filename in sorted(os.listdir(staging), key=lambda n: n == "dataset_info.json"):  # dataset_info last
      os.replace(os.path.join(staging, filename), os.path.join(path, filename))
  except (tf.errors.OpError, OSError) as e:
    if fileio.disk_full(e):
      raise OSError(errno.ENOSPC, f"{fileio.NO_SPACE} while writing metadata", path) from e
    raise
  finally:
    shutil.rmtree(staging, ignore_errors=True)


def write_dataset(path: str, splits: Mapping[str, Sequence[Mapping[str, Any]]],
                  config_summary: Optional[Mapping[str, Any]] = None) -> str:
  """Writes episodes (simulator dicts, see roboshape.sim) as a complete dataset at `path`, without a simulator.

  Args:
    path: the dataset directory (as `roboshape.data.dataset_path` gives); it must not hold a dataset yet.
    splits: {"train": [episode, ...], "val": [...]}; each split's episodes are stored in the given order.
    config_summary: what the dataset was made with (task, resolution, ...); task and resolution are taken from the
      episodes when missing.
  Returns:
    `path`.
  """
  if load_state(path) is not None:
    raise UserError(f"{path} already holds a dataset, which is never rewritten: give another path.")
  first = next(e for episodes in splits.values() for e in episodes)
  summary = dict(config_summary or {})
  summary.setdefault("task", first["task"])
  summary.setdefault("level", first["level"])
  summary.setdefault("resolution", int(first["image"].shape[1]))
  summary.setdefault("depth", "depth" in first)
  summary.setdefault("cameras", list(camera.stored(first)))
  summary.setdefault("state", "state" in first)
  writer = DatasetWriter(path, summary, {k: len(v) for k, v in splits.items()})
  for split, episodes in splits.items():
    size = writer.state["splits"][split]["episodes_per_shard"]
    for start in range(0, len(episodes), size):
      writer.add_shard(split, episodes[start:start + size])
  writer.finish()
  return path
