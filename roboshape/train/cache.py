"""The "cache" stage: every episode of the dataset encoded once by the frozen encoder, for behaviour cloning.

  python launch.py --config=configs/pick_savi.py:tiny --config.stages='("cache",)'

The encoder runs recurrently over each whole episode (`FrozenEncoder.encode_batch`, a scan of its step), so the
cached tokens are exactly those closed-loop control computes frame by frame. Features land in
<workdir>/features/<key>/, where <key> hashes the encoder's identity (checkpoint path and step, or weight-file
hash), the dataset's path and a fingerprint of its files, and the cache dtype: a new encoder checkpoint or a
rewritten dataset gets a new directory, so a stale cache is never read.

Layout of <workdir>/features/<key>/:
  manifest.json                  what was encoded, written last (its presence means the cache is complete)
  <split>/shard_00000.npz ...    `shard_size` episodes each: features [F, N, D], action float32 [F, A],
                                 length int [E] (S frames per episode, F = sum S), seed int [E], success bool [E]
Shards are written atomically, so a killed run resumes at the first missing shard. Features that are not finite
(NaN or inf, from the encoder or from a float16 cache's overflow) are refused in one line naming the episode, and
their shard is not written.
"""
import hashlib
import json
import os
from typing import Dict, Iterable, List, Optional

import numpy as np

from roboshape import fileio
from roboshape import progress
from roboshape import rundir
from roboshape.errors import UserError

SPLITS = ("train", "val")
SHARD_SIZE = 64          # episodes per shard file
BATCH_EPISODES = 8       # episodes encoded together (padded to a common length bucket)
LENGTH_BUCKET = 16       # episode lengths are padded up to a multiple of this, so few shapes compile


def check_config(config) -> None:
  """Raises UserError unless policy.cache_dtype is a float dtype (the cached features' storage)."""
  dtype = config.policy.cache_dtype
  try:
    floating = np.dtype(dtype).kind == "f"
  except TypeError:
    floating = False
  if not floating:
    raise UserError(f"policy.cache_dtype={dtype!r}: use a float dtype, float32 or float16 (halves the cache).")


def dataset_fingerprint(path: str) -> str:
  """A hash of a dataset directory: every file's relative path and size, small files' contents, big files' ends."""
  if not os.path.isdir(path):
    raise UserError(f"dataset {path!r} not found: run the collect stage first (or set --config.data.dir).")
  h = hashlib.sha256()
  for root, dirs, files in os.walk(path):
    dirs.sort()
    for name in sorted(files):
      full = os.path.join(root, name)
      size = os.path.getsize(full)
      h.update(f"{os.path.relpath(full, path)}:{size}\n".encode())
      with open(full, "rb") as f:
        if size <= 1 << 20:
          h.update(f.read())
        else:
          h.update(f.read(1 << 16))
          f.seek(size - (1 << 16))
          h.update(f.read())
  return h.hexdigest()[:16]


def cache_key(encoder_identity: str, dataset_path: str, fingerprint: str, dtype: str) -> str:
  """The cache directory name for one (encoder, dataset, dtype)."""
  text = json.dumps([encoder_identity, os.path.abspath(dataset_path), fingerprint, dtype])
  return hashlib.sha256(text.encode()).hexdigest()[:16]


def _bucket(length: int) -> int:
  return -(-length // LENGTH_BUCKET) * LENGTH_BUCKET


def _encode_group(encoder, episodes: List[dict], dtype) -> List[np.ndarray]:
  """Encodes episodes together: observations padded at the end (the encoder is causal) to one length, batch
  padded. Only the encoder's inputs are read (an episode without one of them is a UserError)."""
  missing = [k for k in encoder.inputs if k not in episodes[0]]
  if missing:
    raise UserError(f"the {encoder.name} encoder needs observation/{', observation/'.join(missing)}, which this "
                    "dataset does not store: collect it again with this version of roboshape into a new "
                    "--config.data.dir (the old dataset still serves the encoders that do not need it).")
  length = _bucket(max(len(e["image"]) for e in episodes))
  videos = {k: [] for k in encoder.inputs}
  for e in episodes:
    for k in encoder.inputs:
      x = np.asarray(e[k])
      videos[k].append(np.concatenate([x, np.repeat(x[-1:], length - len(x), axis=0)], axis=0))
  for k in encoder.inputs:
    while len(videos[k]) < BATCH_EPISODES:
      videos[k].append(videos[k][-1])
  tokens = np.asarray(encoder.encode_batch({k: np.stack(v) for k, v in videos.items()}))   # [B, L, N, D]
  with np.errstate(over="ignore"):     # an overflow of the cache's dtype is refused below, in one line
    features = [tokens[i, :len(e["image"])].astype(dtype) for i, e in enumerate(episodes)]
  for e, encoded, cached in zip(episodes, tokens, features):
    _check_finite(encoder, e, encoded[:len(e["image"])], cached, dtype)
  return features


def _check_finite(encoder, episode: dict, encoded: np.ndarray, cached: np.ndarray, dtype) -> None:
  """A one-line UserError naming the episode when its features, as the encoder gives them or as cached in `dtype`,
  hold a NaN or inf: a policy trained on them would learn NaN, so nothing of their shard is written."""
  bad = ~np.isfinite(cached).reshape(len(cached), -1).all(axis=1)
  if not bad.any():
    return
  frame = int(np.flatnonzero(bad)[0])
  where = (f"episode seed {episode.get('seed', '?')} (frame {frame} of {len(cached)})")
  if np.isfinite(encoded).all():
    raise UserError(f"the {encoder.name} encoder's features of {where} overflow policy.cache_dtype={dtype!r} "
                    f"(largest |value| {float(np.abs(encoded).max()):.4g}): cache them as float32 "
                    "(--config.policy.cache_dtype=float32); nothing of their shard was written.")
  raise UserError(f"the {encoder.name} encoder ({encoder.identity}) gives non-finite features (NaN or inf) for "
                  f"{where}; nothing of their shard was written. The encoder is broken (a pretrained one: its "
                  "pretraining diverged, pretrain it again, e.g. with --redo=pretrain and a lower "
                  "--config.pretrain.train.learning_rate) or its inputs are (`python -m roboshape.data.validate "
                  "<dataset>`).")


def _step_actions(episode: dict) -> np.ndarray:
  """float32 [S, A], one row per frame: an episode of T actions and T + 1 frames gets a zero last row (RLDS)."""
  action = np.asarray(episode["action"], np.float32)
  missing = len(episode["image"]) - len(action)
  if missing < 0 or missing > 1:
    raise ValueError(f"episode with {len(episode['image'])} frames and {len(action)} actions")
  return np.concatenate([action, np.zeros((missing, action.shape[1]), np.float32)], axis=0)


def _write_shard(path: str, episodes: List[dict], features: List[np.ndarray]) -> None:
  """Writes one shard atomically (fileio.atomic_write_file: a failed write, e.g. on a full disk, leaves none)."""
  arrays = dict(features=np.concatenate(features, axis=0),
                action=np.concatenate([_step_actions(e) for e in episodes], axis=0),
                length=np.asarray([len(e["image"]) for e in episodes], np.int64),
                seed=np.asarray([int(e.get("seed", -1)) for e in episodes], np.int64),
                success=np.asarray([bool(e.get("success", True)) for e in episodes], bool))
  fileio.atomic_write_file(path, lambda f: np.savez(f, **arrays))


def encode_split(encoder, episodes: Iterable[dict], out_dir: str, dtype: str = "float32",
                 desc: str = "encode") -> int:
  """Encodes `episodes` (dicts with image uint8 [S, H, W, 3], the encoder's other inputs [S, ...] and action
  [S, A]) into shards under `out_dir`.

  Resumes: shards already in `out_dir` are kept and their episodes skipped. Returns the number of episodes.
  """
  os.makedirs(out_dir, exist_ok=True)
  done = 0
  while os.path.exists(os.path.join(out_dir, f"shard_{done:05d}.npz")):
    done += 1
  count, shard = 0, []
  bar = progress.bar(desc=desc, unit="episode")
  def flush_shard(index):
    # Sort by length inside the shard so padded batches waste little.
    order = sorted(range(len(shard)), key=lambda i: len(shard[i]["image"]))
    by_index = {}
    for g in range(0, len(order), BATCH_EPISODES):
      idx = order[g:g + BATCH_EPISODES]
      for i, f in zip(idx, _encode_group(encoder, [shard[i] for i in idx], dtype)):
        by_index[i] = f
      bar.update(len(idx))
    feats = [by_index[i] for i in range(len(shard))]
    _write_shard(os.path.join(out_dir, f"shard_{index:05d}.npz"), shard, feats)
  try:
    for episode in episodes:
      index = count // SHARD_SIZE
      count += 1
      if index < done:
        bar.update(1)
        continue
      shard.append(episode)
      if len(shard) == SHARD_SIZE:
        flush_shard(index)
        shard = []
    if shard:
      flush_shard((count - 1) // SHARD_SIZE)
  finally:
    bar.close()      # also before an error's one line, which then ends the output
  return count


def load_split(feature_dir: str, split: str) -> Dict[str, np.ndarray]:
  """All shards of a split: features [F, N, D], action [F, A], offsets int [E + 1], seed [E], success [E]."""
  split_dir = os.path.join(feature_dir, split)
  names = sorted(n for n in os.listdir(split_dir) if n.startswith("shard_") and n.endswith(".npz")
                 and ".tmp" not in n) if os.path.isdir(split_dir) else []
  if not names:
    raise UserError(f"no cached features in {split_dir}: run the cache stage first.")
  parts = [dict(np.load(os.path.join(split_dir, n))) for n in names]
  lengths = np.concatenate([p["length"] for p in parts])
  return dict(
      features=np.concatenate([p["features"] for p in parts], axis=0),
      action=np.concatenate([p["action"] for p in parts], axis=0),
      offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
      seed=np.concatenate([p["seed"] for p in parts]),
      success=np.concatenate([p["success"] for p in parts]))


def feature_dir(config, workdir: str, encoder) -> str:
  """<workdir>/features/<key> for this config's dataset and this encoder."""
  from roboshape import data  # pylint: disable=import-outside-toplevel
  path = data.dataset_path(config, workdir)
  key = cache_key(encoder.identity, path, dataset_fingerprint(path), config.policy.cache_dtype)
  return rundir.features_dir(workdir, key)


def build(config, workdir: str, encoder, episode_source=None) -> str:
  """Encodes the config's dataset with `encoder` unless its cache is complete; returns the feature directory.

  `episode_source(split) -> iterator of episodes` defaults to `roboshape.data.reader.read_episodes`.
  """
  from roboshape import data  # pylint: disable=import-outside-toplevel
  path = data.dataset_path(config, workdir)
  fingerprint = dataset_fingerprint(path)
  key = cache_key(encoder.identity, path, fingerprint, config.policy.cache_dtype)
  out = rundir.features_dir(workdir, key)
  manifest_path = os.path.join(out, "manifest.json")
  if os.path.exists(manifest_path):
    print(f"[cache] features already cached in {out}", flush=True)
    return out
  if episode_source is None:
    from roboshape.data import reader  # pylint: disable=import-outside-toplevel
    episode_source = lambda split: reader.read_episodes(path, split)
  counts = {}
  for split in SPLITS:
    counts[split] = encode_split(encoder, episode_source(split), os.path.join(out, split),
                                 config.policy.cache_dtype, desc=f"encode {split}")
  manifest = dict(encoder=encoder.name, encoder_identity=encoder.identity, dataset=os.path.abspath(path),
                  dataset_fingerprint=fingerprint, dtype=config.policy.cache_dtype,
                  num_tokens=encoder.num_tokens, token_dim=encoder.token_dim, episodes=counts)
  fileio.atomic_write_json(manifest_path, manifest)
  return out


def run(config, workdir: str) -> None:
  """The cache stage: encodes the dataset with the config's frozen encoder (skipped when already cached)."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  build(config, workdir, encoders.build_encoder(config, workdir))


def read_manifest(feature_path: str) -> Optional[dict]:
  path = os.path.join(feature_path, "manifest.json")
  if not os.path.exists(path):
    return None
  with open(path) as f:
    return json.load(f)
