"""Reading the RoboShape dataset: whole episodes as numpy, and endless batches of video clips for training.

  for ep in read_episodes(path, "train"):          # image uint8 [S,H,W,3], action float32 [S,7], seed, ...
  for batch in clip_batches(path, "train", clip_length=6, batch_size=8, seed=0):
    batch["video"]                                 # uint8 [B, L, H, W, 3]

Both read through TFDS (`tfds.builder_from_directory`) and tf.data. `clip_batches` holds the split's frames in
memory (about 16 KB per frame at 64x64: 0.25 GB for 200 episodes) and draws batch b from a random generator seeded
by (seed, b), so the same seed gives the same batches and `start_batch=b` resumes exactly where batch b was.
"""
import json
import os
from typing import Any, Dict, Iterator, List, Optional, Sequence

import numpy as np
import tensorflow as tf
import tensorflow_datasets as tfds

from roboshape import data as data_lib
from roboshape.envs import camera
from roboshape.errors import UserError

_MAX_STEPS = 1 << 20


def load_state(path: str) -> Dict[str, Any]:
  """roboshape.json of the dataset at `path`; a missing dataset is a UserError that says how to make one."""
  state_path = os.path.join(path, data_lib.STATE_FILE)
  if not os.path.exists(os.path.join(path, "dataset_info.json")) or not os.path.exists(state_path):
    raise UserError(f"no RoboShape dataset at {path}: run the collect stage first "
                    "(python launch.py --config=configs/<task>_savi.py --config.stages=collect --workdir=...).")
  with open(state_path) as f:
    return json.load(f)


def check_complete(path: str, state: Dict[str, Any]) -> None:
  if not state.get("complete"):
    counts = ", ".join(f"{k} {sum(len(s['seeds']) for s in v['shards'])}/{v['target']}"
                       for k, v in state["splits"].items())
    raise UserError(f"the dataset at {path} is incomplete ({counts} episodes): run the collect stage again "
                    "with the same config to finish it.")


def _flatten(example: Dict[str, Any]) -> Dict[str, tf.Tensor]:
  """An RLDS episode (steps as a nested tf.data.Dataset) -> one dict of [S, ...] tensors."""
  steps = example["steps"].batch(_MAX_STEPS).get_single_element()
  meta = example["episode_metadata"]
  optional = {k: v for k, v in steps["observation"].items() if k not in ("image", "segmentation")}  # depth, wrist_*
  return {
      **optional,
      "image": steps["observation"]["image"],
      "segmentation": steps["observation"]["segmentation"],
      "action": steps["action"],
      "reward": steps["reward"],
      "discount": steps["discount"],
      "is_first": steps["is_first"],
      "is_last": steps["is_last"],
      "is_terminal": steps["is_terminal"],
      "seed": meta["seed"],
      "success": meta["success"],
      "task": meta["task"],
      "level": meta["level"],
      "env_version": meta["env_version"],
  }


def _to_python(episode: Dict[str, Any]) -> Dict[str, Any]:
  for key in ("task", "level", "env_version"):
    episode[key] = episode[key].decode()
  episode["seed"] = int(episode["seed"])
  episode["success"] = bool(episode["success"])
  return episode


def _iterate(ds: tf.data.Dataset, path: str, state: Dict[str, Any], split: str) -> Iterator[Dict[str, Any]]:
  ds = ds.map(_flatten, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True).prefetch(2)
  try:
    for episode in tfds.as_numpy(ds):
      episode = _to_python(episode)
      broken = data_lib.non_finite(episode)
      if broken:
        raise UserError(f"episode seed {episode['seed']} of split {split!r} in the dataset at {path} has non-finite "
                        f"{broken} (NaN or inf), which no stage can learn from: `python -m roboshape.data.validate "
                        f"{path}` lists every such episode; collect a new dataset into another --config.data.dir.")
      yield episode
  except tf.errors.OpError as e:   # DataLossError on a truncated or corrupted record, NotFoundError, ...
    raise _damaged(path, state, split, e) from None


def _damaged(path: str, state: Dict[str, Any], split: str, error: Exception) -> UserError:
  """The one-line UserError for a shard of `split` that fails to read, naming it when its checksum tells which."""
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
  found = rlds.shard_problems(path, state, splits=(split,))
  if found:
    return _shard_error(path, found[0])
  first = (str(error).strip().splitlines() or [type(error).__name__])[0][:200]
  return UserError(f"reading split {split!r} of the dataset at {path} failed ({type(error).__name__}: {first}); "
                   f"run `python -m roboshape.data.validate {path}` to find the damaged shard, then the collect "
                   "stage again to re-collect it.")


def _shard_error(path: str, problem: Dict[str, Any]) -> UserError:
  return UserError(f"shard {os.path.join(path, problem['file'])} is {problem['problem']}: run the collect stage "
                   "again to re-collect it (it re-collects damaged shards), or "
                   f"`python -m roboshape.data.validate {path}` to check the whole dataset.")


def check_shards(path: str, state: Dict[str, Any], split: str) -> None:
  """A UserError naming the first shard of `split` that is missing or not of its recorded size (cheap: no hash)."""
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
  found = rlds.shard_problems(path, state, splits=(split,), hashes=False)
  if found:
    raise _shard_error(path, found[0])


def read_episodes(path: str, split: str, allow_incomplete: bool = False) -> Iterator[Dict[str, Any]]:
  """The episodes of a split in their stored order (seed order), as numpy.

  Yields dicts with image uint8 [S,H,W,3], segmentation uint8 [S,H,W], (depth uint16 [S,H,W] in millimetres, in
  a dataset collected with env.depth=True), action float32 [S,7], reward float32 [S],
  discount float32 [S], is_first / is_last / is_terminal bool [S], seed int, success bool, task, level,
  env_version str; S = T + 1 (the last step holds the final frame and a zero action).
  allow_incomplete: read a dataset whose collection has not finished (tools); training refuses one.
  A missing, truncated or corrupted shard is a one-line UserError naming it (sizes are checked before reading,
  checksums when a record fails to decode), and so is an episode whose actions or states hold a NaN or inf.
  """
  state = load_state(path)
  if not allow_incomplete:
    check_complete(path, state)
  if split not in state["splits"]:
    raise UserError(f"unknown split {split!r}; the dataset at {path} has {', '.join(state['splits'])}.")
  if not state["splits"][split]["shards"]:
    return iter(())
  check_shards(path, state, split)
  builder = tfds.builder_from_directory(path)
  # No autocache: every call builds a fresh pipeline that is read once, so TFDS's in-memory cache of a small split
  # would only copy it (and warn when a caller stops early, as pretraining's first val episodes do).
  read_config = tfds.ReadConfig(try_autocache=False)
  return _iterate(builder.as_dataset(split=split, shuffle_files=False, read_config=read_config), path, state, split)


class ShardReader:
  """Reads single shard files (for validation, so a broken file is named): `read(file) -> Iterator[episode]`.

  The decoder is traced once and shared by all shards; a truncated or corrupted file raises tf.errors.DataLossError
  (or another tf.errors.OpError) while iterating.
  """

  def __init__(self, summary: Dict[str, Any]):
    """summary: the dataset's config as roboshape.json records it (resolution, depth, state, cameras)."""
    from roboshape.data import rlds  # pylint: disable=import-outside-toplevel
    feats = rlds.features_of(summary)
    self._decode = tf.function(lambda record: _flatten(feats.deserialize_example(record)))

  def read(self, file: str) -> Iterator[Dict[str, Any]]:
    for record in tf.data.TFRecordDataset(file):
      yield _to_python(tf.nest.map_structure(lambda t: t.numpy(), self._decode(record)))


class _ClipTable:
  """All frames of a split in memory plus the (episode, start) of every clip of `clip_length` frames."""

  def __init__(self, episodes: Sequence[Dict[str, Any]], clip_length: int):
    lengths = np.array([e["image"].shape[0] for e in episodes], np.int64)
    self.images = np.concatenate([e["image"] for e in episodes])
    self.segmentations = np.concatenate([e["segmentation"] for e in episodes])
    self.depths = np.concatenate([e["depth"] for e in episodes]) if "depth" in episodes[0] else None
    self.seeds = np.array([e["seed"] for e in episodes], np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    clips_per_episode = np.maximum(lengths - clip_length + 1, 0)
    self.clip_episode = np.repeat(np.arange(len(episodes)), clips_per_episode)
    self.clip_start = np.concatenate([np.arange(n) for n in clips_per_episode]).astype(np.int64)
    self.offsets = offsets
    self.clip_length = clip_length

  def batch(self, seed: int, index: int, batch_size: int) -> List[np.ndarray]:
    rng = np.random.default_rng([seed, index])
    clips = rng.integers(0, len(self.clip_episode), size=batch_size)
    episode, start = self.clip_episode[clips], self.clip_start[clips]
    frames = self.offsets[episode][:, None] + start[:, None] + np.arange(self.clip_length)[None]
    out = [self.images[frames], self.segmentations[frames], self.seeds[episode], start]
    return out + ([self.depths[frames]] if self.depths is not None else [])


def clip_batches(path: str, split: str, clip_length: int, batch_size: int, seed: int = 0,
                 start_batch: int = 0, cameras: Sequence[str] = camera.DEFAULT) -> Iterator[Dict[str, np.ndarray]]:
  """Endless batches of random clips (uniform over all clips of `clip_length` consecutive frames, of every camera
  of `cameras`: each view of an episode is one more source of clips, under the front camera's names).

  Batch b depends only on (path, split, clip_length, batch_size, seed, cameras, b): `start_batch=b` resumes the
  sequence.
  Yields video uint8 [B, L, H, W, 3], segmentation uint8 [B, L, H, W], episode_seed int64 [B], start int64 [B]
  (the clip's first step within its episode), and depth uint16 [B, L, H, W] (millimetres) in a dataset with depth.
  """
  if clip_length < 1 or batch_size < 1:
    raise UserError(f"clip_length ({clip_length}) and batch_size ({batch_size}) must be >= 1.")
  episodes = [camera.view(e, c) for e in read_episodes(path, split) for c in cameras]
  if not episodes:
    raise UserError(f"split {split!r} of {path} has no episodes.")
  table = _ClipTable(episodes, clip_length)
  if not len(table.clip_episode):
    raise UserError(f"no episode of split {split!r} in {path} has {clip_length} frames; lower the clip length.")
  res = table.images.shape[1:3]

  def make(index):
    return table.batch(seed, int(index), batch_size)

  with_depth = table.depths is not None

  def fetch(index):
    dtypes = [tf.uint8, tf.uint8, tf.int64, tf.int64] + ([tf.uint16] if with_depth else [])
    video, segmentation, episode_seed, start, *depth = tf.numpy_function(make, [index], dtypes, stateful=False)
    video.set_shape((batch_size, clip_length, *res, 3))
    segmentation.set_shape((batch_size, clip_length, *res))
    episode_seed.set_shape((batch_size,))
    start.set_shape((batch_size,))
    batch = {"video": video, "segmentation": segmentation, "episode_seed": episode_seed, "start": start}
    if with_depth:
      depth[0].set_shape((batch_size, clip_length, *res))
      batch["depth"] = depth[0]
    return batch

  ds = tf.data.Dataset.range(start_batch, np.iinfo(np.int64).max)
  ds = ds.map(fetch, num_parallel_calls=2, deterministic=True).prefetch(2)
  return iter(tfds.as_numpy(ds))


def dataset_summary(path: str) -> Optional[Dict[str, Any]]:
  """The config a dataset was collected with (roboshape.json's "config"), or None when there is no dataset."""
  try:
    return load_state(path)["config"]
  except UserError:
    return None
