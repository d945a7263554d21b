"""Checks a RoboShape dataset end to end; exits non-zero with the reasons when anything is off.

  python -m roboshape.data.validate PATH       # PATH: the dataset, or a workdir / data folder holding one

Checks: the collection finished and every split has its episode count; the TFDS metadata agrees with roboshape.json;
every shard has its recorded size and sha256 and decodes (truncated or corrupted shards are named); per episode the
recorded seed, success, task, shapes and dtypes, step flags (is_first, is_last, is_terminal), actions finite and in
[-1, 1] with a zero last action, no blank (constant) frame, segmentation ids in range; seeds unique within a split
and disjoint across splits. Prints a per-split summary (episodes, steps, expert failures, bytes per frame).
Exit status: 0 valid, 1 invalid (reasons on stderr), 2 no dataset / bad arguments.
"""
import argparse
import os
import sys
from typing import Any, Dict, List

import numpy as np

from roboshape import data as data_lib
from roboshape import errors
from roboshape.errors import UserError
from roboshape.envs import camera
from roboshape.envs import ids
from roboshape.envs import state as state_lib

_ACTION_TOL = 1e-6
_MAX_SHOWN = 20


def find_dataset(path: str) -> str:
  """`path` itself when it holds a dataset, else the one dataset under a workdir or data folder.

  Looks for <root>/roboshape_<task>/1.0.0 with root `path`, `path`/data, and their subfolders (a grid's
  <workdir>/data/<task>/, configs/reproduce.py).
  """
  if os.path.exists(os.path.join(path, data_lib.STATE_FILE)):
    return path
  found = []
  roots = [path, os.path.join(path, "data")]
  roots += [os.path.join(r, d) for r in roots if os.path.isdir(r) for d in sorted(os.listdir(r))
            if not d.startswith("roboshape_") and os.path.isdir(os.path.join(r, d))]
  for root in dict.fromkeys(os.path.normpath(r) for r in roots):
    if os.path.isdir(root):
      for name in sorted(os.listdir(root)):
        candidate = os.path.join(root, name, data_lib.VERSION)
        if name.startswith("roboshape_") and os.path.exists(os.path.join(candidate, data_lib.STATE_FILE)):
          found.append(candidate)
  if len(found) == 1:
    return found[0]
  if not found:
    raise UserError(f"no RoboShape dataset at {path} (no {data_lib.STATE_FILE}); give the dataset directory, "
                    "e.g. <workdir>/data/roboshape_pick/1.0.0.")
  raise UserError(f"{path} holds several datasets, name one: {', '.join(found)}")


def _check_episode(ep: Dict[str, Any], expected_seed: int, config: Dict[str, Any], where: str) -> List[str]:
  problems = []
  res = int(config["resolution"])
  action, num_steps = ep["action"], ep["image"].shape[0]
  if ep["seed"] != expected_seed:
    problems.append(f"{where}: seed {ep['seed']}, roboshape.json records {expected_seed}")
  if not ep["success"]:
    problems.append(f"{where}: a failed expert episode was stored")
  if ep["task"] != config["task"] or ep["level"] != config["level"]:
    problems.append(f"{where}: task/level {ep['task']}/{ep['level']}, "
                    f"the dataset is {config['task']}/{config['level']}")
  for name in config.get("cameras", camera.DEFAULT):      # each camera's frames (roboshape/envs/camera.py)
    image_key, seg_key, depth_key = camera.keys(name)
    image, seg = ep.get(image_key), ep.get(seg_key)
    if image is None or image.dtype != np.uint8 or image.shape != (num_steps, res, res, 3):
      problems.append(f"{where}: {image_key} {getattr(image, 'dtype', None)} {getattr(image, 'shape', None)}, "
                      f"want uint8 [{num_steps},{res},{res},3]")
    if seg is None or seg.dtype != np.uint8 or seg.shape != (num_steps, res, res):
      problems.append(f"{where}: {seg_key} {getattr(seg, 'dtype', None)} {getattr(seg, 'shape', None)}, "
                      f"want uint8 [{num_steps},{res},{res}]")
    if config.get("depth", False):
      depth = ep.get(depth_key)
      if depth is None or depth.dtype != np.uint16 or depth.shape != (num_steps, res, res):
        problems.append(f"{where}: {depth_key} {getattr(depth, 'dtype', None)} {getattr(depth, 'shape', None)}, "
                        f"want uint16 [{num_steps},{res},{res}]")
      elif not depth.any():
        problems.append(f"{where}: {depth_key} is zero everywhere")
  if config.get("state", False):
    state = ep.get("state")
    if state is None or state.dtype != np.float32 or state.shape != (num_steps, state_lib.DIM):
      problems.append(f"{where}: state {getattr(state, 'dtype', None)} {getattr(state, 'shape', None)}, "
                      f"want float32 [{num_steps},{state_lib.DIM}]")
    elif not np.all(np.isfinite(state)):
      problems.append(f"{where}: state has non-finite values")
  if action.dtype != np.float32 or action.shape != (num_steps, 7):
    problems.append(f"{where}: action {action.dtype} {action.shape}, want float32 [{num_steps},7]")
    return problems
  if num_steps < 2:
    problems.append(f"{where}: {num_steps} step(s); an episode needs at least one action")
  if not np.all(np.isfinite(action)) or np.abs(action).max(initial=0) > 1 + _ACTION_TOL:
    problems.append(f"{where}: actions outside [-1, 1] (max |a| = {np.abs(action).max():.4g})")
  if np.any(action[-1] != 0):
    problems.append(f"{where}: the last step's action is not zero")
  image, seg = ep["image"], ep["segmentation"]             # the front view's
  if image.shape != (num_steps, res, res, 3) or seg.shape != (num_steps, res, res):
    return problems
  flat = image.reshape(num_steps, -1)
  blank = np.nonzero(flat.min(axis=1) == flat.max(axis=1))[0]
  if len(blank):
    problems.append(f"{where}: blank (constant) frame(s) at steps {blank[:5].tolist()}")
  max_id = ids.FIRST_DISTRACTOR - 1 + int(config.get("max_distractors", 4))   # the hand (ids.HAND) may lie above
  if seg.size and int(seg.max()) > max_id:
    bad = [int(i) for i in np.unique(seg) if i > max_id and i != ids.HAND]
    if bad:
      problems.append(f"{where}: segmentation id {bad[-1]} > {max_id} (and not the hand's {ids.HAND})")
  want_first = np.arange(num_steps) == 0
  want_last = np.arange(num_steps) == num_steps - 1
  if not np.array_equal(ep["is_first"], want_first) or not np.array_equal(ep["is_last"], want_last):
    problems.append(f"{where}: is_first/is_last flags are not on the first/last step only")
  if np.any(ep["is_terminal"][:-1]):
    problems.append(f"{where}: is_terminal set before the last step")
  if not np.all(np.isfinite(ep["reward"])):
    problems.append(f"{where}: non-finite reward")
  return problems


def validate(path: str) -> Dict[str, Any]:
  """Checks the dataset at `path`; returns {"problems": [str], "splits": {split: stats}}."""
  import tensorflow as tf  # pylint: disable=import-outside-toplevel
  import tensorflow_datasets as tfds  # pylint: disable=import-outside-toplevel
  from roboshape.data import reader  # pylint: disable=import-outside-toplevel
  from roboshape.data import rlds  # pylint: disable=import-outside-toplevel

  state = rlds.load_state(path)
  if state is None:
    raise UserError(f"no RoboShape dataset at {path}.")
  config = state["config"]
  problems: List[str] = []
  stats: Dict[str, Dict[str, Any]] = {}
  if not state["complete"]:
    problems.append("the collection has not finished (complete: false); run the collect stage again")
  try:
    splits_info = tfds.builder_from_directory(path).info.splits
  except Exception as e:  # pylint: disable=broad-except
    problems.append(f"TFDS cannot read the metadata: {str(e).strip().splitlines()[0]}")
    splits_info = {}
  seen: Dict[int, str] = {}
  shard_reader = reader.ShardReader(config)
  for split, info in state["splits"].items():
    shards = info["shards"]
    recorded = [len(s["seeds"]) for s in shards]
    tfds_lengths = list(splits_info[split].shard_lengths) if split in splits_info else []
    if tfds_lengths != recorded:
      problems.append(f"{split}: TFDS metadata lists shard lengths {tfds_lengths}, roboshape.json {recorded}")
    if sum(recorded) != info["target"]:
      problems.append(f"{split}: {sum(recorded)} episodes, the config asks {info['target']}")
    lengths, failures = [], sum(len(s["failed_seeds"]) for s in shards)
    for shard in shards:
      file = os.path.join(path, shard["file"])
      if not os.path.exists(file):
        problems.append(f"{split}: shard {shard['file']} is missing")
        continue
      size = os.path.getsize(file)
      if size != shard["num_bytes"]:
        problems.append(f"{split}: shard {shard['file']} is truncated or changed ({size} bytes, "
                        f"{shard['num_bytes']} recorded)")
      elif rlds.file_sha256(file) != shard["sha256"]:
        problems.append(f"{split}: shard {shard['file']} is corrupted (sha256 differs from the recorded one)")
      decoded = 0
      try:
        for i, ep in enumerate(shard_reader.read(file)):
          seed = shard["seeds"][i] if i < len(shard["seeds"]) else -1
          problems += _check_episode(ep, seed, config, f"{split} {shard['file']} episode {i}")
          lengths.append(ep["image"].shape[0])
          decoded += 1
      except (tf.errors.OpError, ValueError) as e:
        problems.append(f"{split}: shard {shard['file']} cannot be decoded "
                        f"({type(e).__name__}: {str(e).strip().splitlines()[0][:200]})")
        continue
      if decoded != len(shard["seeds"]):
        problems.append(f"{split}: shard {shard['file']} holds {decoded} episodes, {len(shard['seeds'])} recorded")
    for shard in shards:
      for seed in shard["seeds"] + shard["failed_seeds"]:
        if seed in seen:
          problems.append(f"seed {seed} appears twice ({seen[seed]} and {split})")
        seen[seed] = split
    num_bytes = sum(s["num_bytes"] for s in shards)
    stats[split] = {"episodes": len(lengths), "steps": int(sum(lengths)), "failures": failures,
                    "min_len": min(lengths, default=0), "max_len": max(lengths, default=0),
                    "bytes": num_bytes, "bytes_per_frame": num_bytes / max(1, sum(lengths))}
  return {"problems": problems, "splits": stats, "config": config, "env_version": state["env_version"]}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m roboshape.data.validate", description=__doc__.splitlines()[0])
  parser.add_argument("path", help="the dataset directory, or a workdir / data folder holding one dataset")
  args = parser.parse_args(argv)
  try:
    path = find_dataset(args.path)
    result = validate(path)
  except UserError as e:
    return errors.print_error(e)
  cfg = result["config"]
  print(f"{path}: task {cfg['task']}, level {cfg['level']}, {cfg['resolution']}x{cfg['resolution']}, "
        f"env {result['env_version']}")
  for split, s in result["splits"].items():
    tried = s["episodes"] + s["failures"]
    print(f"  {split:5s} {s['episodes']:6d} episodes {s['steps']:8d} steps (length {s['min_len']}-{s['max_len']}), "
          f"{s['failures']} expert failures ({100 * s['episodes'] / max(1, tried):.1f}% success), "
          f"{s['bytes'] / 1e6:.1f} MB, {s['bytes_per_frame']:.0f} bytes/frame")
  problems = result["problems"]
  if problems:
    for p in problems[:_MAX_SHOWN]:
      print(f"INVALID: {p}", file=sys.stderr)
    if len(problems) > _MAX_SHOWN:
      print(f"INVALID: ... and {len(problems) - _MAX_SHOWN} more", file=sys.stderr)
    return 1
  print("OK: the dataset is valid")
  return 0


if __name__ == "__main__":
  sys.exit(main())
