"""The RoboShape dataset: expert demonstrations stored as RLDS episodes in TFDS, one dataset per task.

  path = roboshape.data.dataset_path(config, workdir)       # <config.data.dir or workdir/data>/roboshape_<task>/1.0.0
  ds = tfds.builder_from_directory(path).as_dataset(split="train")   # plain TFDS, nothing of roboshape needed

Modules: `rlds` (layout + writer), `reader` (episodes and clip batches), `collect` (the "collect" stage),
`validate` and `browse` (command-line tools). Importing this package is cheap: TensorFlow is imported only by the
modules that read or write.

A dataset's identity (`identity`, `record`, `read_record`) is a hash over its shards' sha256 as its roboshape.json
records them: it names what the dataset holds, not where it lies, so every copy of a dataset has the same identity
and a dataset with any shard changed, added or removed has another. Each run records the identity of the dataset
it was trained on (<workdir>/dataset.json, written by the collect stage), and so does each published cell.
"""
import hashlib
import json
import os
from typing import Any, Dict, Mapping, Optional

from roboshape import rundir
from roboshape.errors import UserError

VERSION = "1.0.0"
SPLITS = ("train", "val")
STATE_FILE = "roboshape.json"  # roboshape's own record of a dataset: its config, shards, seeds and checksums


def dataset_name(task: str) -> str:
  """The TFDS name of the dataset of one task, e.g. "roboshape_pick"."""
  return f"roboshape_{task}"


def dataset_path(config, workdir: str) -> str:
  """The directory `tfds.builder_from_directory` reads: <rundir.data_root>/roboshape_<task>/<VERSION>."""
  return os.path.join(rundir.data_root(config, workdir), dataset_name(config.task), VERSION)


def read_state(path: str) -> Optional[Dict[str, Any]]:
  """The roboshape.json of the dataset at `path` as it is, or None when there is none; a UserError when it cannot be
  read."""
  state_path = os.path.join(path, STATE_FILE)
  if not os.path.exists(state_path):
    return None
  try:
    with open(state_path, encoding="utf-8") as f:
      state = json.load(f)
    if not isinstance(state, dict):
      raise ValueError(f"a JSON {type(state).__name__}, not a record")
  except (OSError, ValueError) as e:
    raise UserError(f"{state_path} is unreadable ({e}): the dataset's record is damaged. Copy it back from a "
                    "backup if you have one; otherwise collect a new dataset into another --config.data.dir (or "
                    f"move {path} away and collect again). It is left as it is.") from None
  return state


def identity(state: Mapping[str, Any]) -> str:
  """16 hex digits of the sha256 of every split's shard checksums, in shard order, from a roboshape.json."""
  checksums = {split: [shard["sha256"] for shard in info["shards"]] for split, info in state["splits"].items()}
  return hashlib.sha256(json.dumps(checksums, sort_keys=True).encode()).hexdigest()[:16]


def record(state: Mapping[str, Any]) -> Dict[str, Any]:
  """What a run records of its dataset (rundir.DATASET_FILE): its identity, name, whether it was complete, the
  simulator's env version, and episodes and shards per split; no path."""
  return dict(identity=identity(state), name=state["name"], complete=bool(state.get("complete")),
              env_version=state.get("env_version"),
              episodes={split: sum(len(s["seeds"]) for s in info["shards"]) for split, info in state["splits"].items()},
              shards={split: len(info["shards"]) for split, info in state["splits"].items()})


def read_record(path: str) -> Optional[Dict[str, Any]]:
  """`record` of the dataset at `path` (its roboshape.json), or None when there is none there."""
  state = read_state(path)
  if state is None:
    return None
  try:
    return record(state)
  except (KeyError, TypeError) as e:
    raise UserError(f"{os.path.join(path, STATE_FILE)} lacks its shard records ({type(e).__name__}: {e}): collect "
                    "the dataset again into another --config.data.dir.") from None


def non_finite(episode: Mapping[str, Any]) -> Optional[str]:
  """Where an episode's actions or privileged states first hold a NaN or inf, e.g. "actions at step 3", or None
  when they are finite (an episode without states has only its actions checked)."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  for key, name in (("action", "actions"), ("state", "states")):
    if key not in episode:
      continue
    values = np.asarray(episode[key])
    if not np.issubdtype(values.dtype, np.floating):
      continue
    bad = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    if bad.any():
      return f"{name} at step {int(np.flatnonzero(bad)[0])}"
  return None
