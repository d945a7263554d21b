"""The "collect" stage: expert demonstrations from the simulator workers into a RoboShape dataset (RLDS in TFDS).

  python launch.py --config=configs/pick_savi.py:small --config.stages=collect --workdir=runs/pick

Seeds: split s uses the candidate seeds SEED_BASES[s], SEED_BASES[s] + 1, ... (train and val never share one) and
keeps the first N whose expert succeeds, in seed order; failures are counted, recorded in roboshape.json with the
seed, reported, and replaced by the next seeds. So a config always gives the same episodes, whatever the number of
workers or the order they finish in.

Processes: the SAPIEN workers (roboshape.sim.SimPool, spawned) run the expert and send numpy episodes; this process
never imports SAPIEN and writes them with TFDS. Shards are committed atomically in seed order (see rlds.py), so a
run killed at any moment (SIGKILL included) and started again with the same command re-collects only the seeds
after the last committed shard: nothing is lost and nothing is written twice. A complete dataset is never
rewritten; a dataset of another config in the same place is refused.

Damaged shards: whenever it finds a dataset, the stage checks every recorded shard's size and sha256 against
roboshape.json (a fraction of a second for a :small dataset) and re-collects a missing, truncated or corrupted shard from its
recorded seeds; the new file replaces it only when it is byte for byte the recorded one (`repair_shards`).
A successful episode with a NaN or inf action or state stops the collection in one line naming its seed, before
anything of it is written.
"""
import contextlib
import fcntl
import os
import time
from typing import Any, Dict, Iterator, List, Mapping, Sequence

import tqdm

from roboshape import data as data_lib
from roboshape import fileio
from roboshape import progress as progress_lib
from roboshape import rundir
from roboshape.errors import DiskFull
from roboshape.errors import UserError
from roboshape.data import rlds
from roboshape.envs import camera

LEVEL = "train"
SEED_BASES = {"train": 0, "val": 1_000_000}
# The fields of a config that decide a dataset's content: a stored dataset must match them all.
_SUMMARY_FIELDS = ("task", "level", "resolution", "min_distractors", "max_distractors", "max_episode_steps",
                   "train_episodes", "val_episodes", "train_seed_base", "val_seed_base", "depth", "cameras")
# Values of fields that datasets written before the field existed do not record.
_SUMMARY_DEFAULTS = {"depth": False, "cameras": list(camera.DEFAULT)}
_MAX_WORKER_RESTARTS = 3


def split_targets(config) -> Dict[str, int]:
  """Episodes per split: train from the config, val = max(min_val_episodes, round(val_fraction * train))."""
  train = int(config.data.train_episodes)
  if train < 1:
    raise UserError(f"config.data.train_episodes must be >= 1 (got {train}).")
  val = max(int(config.data.min_val_episodes), int(round(float(config.data.val_fraction) * train)))
  return {"train": train, "val": val}


def config_summary(config) -> Dict[str, Any]:
  """What a dataset is made of: the config fields that change its episodes."""
  targets = split_targets(config)
  return {
      "task": config.task,
      "level": LEVEL,
      "resolution": int(config.env.resolution),
      "min_distractors": int(config.env.min_distractors),
      "max_distractors": int(config.env.max_distractors),
      "max_episode_steps": int(config.env.max_episode_steps),
      "train_episodes": targets["train"],
      "val_episodes": targets["val"],
      "train_seed_base": SEED_BASES["train"],
      "val_seed_base": SEED_BASES["val"],
      "depth": bool(config.env.depth),
      "cameras": list(config.env.cameras),     # a list, as roboshape.json stores it
      # Every dataset collected now stores the privileged state; not compared (_SUMMARY_FIELDS): a dataset of an
      # earlier version, without it, serves every encoder that does not need it.
      "state": True,
  }


def config_differences(stored: Mapping[str, Any], wanted: Mapping[str, Any]) -> list:
  """Human-readable differences, e.g. ["resolution: 32 in the dataset, 64 in the config"]."""
  return [f"{key}: {old!r} in the dataset, {new!r} in the config"
          for key, old, new in summary_differences(stored, wanted)]


def summary_differences(stored: Mapping[str, Any], wanted: Mapping[str, Any]) -> list:
  """[(summary field, stored value, wanted value)] where two datasets' summaries (`config_summary`) differ."""
  def value(summary, key):
    return summary.get(key, _SUMMARY_DEFAULTS.get(key))
  return [(key, value(stored, key), value(wanted, key)) for key in _SUMMARY_FIELDS
          if value(stored, key) != value(wanted, key)]


# The config field each summary field comes from (val_episodes: from data.val_fraction and data.min_val_episodes).
CONFIG_FIELDS = {"task": "task", "resolution": "env.resolution", "min_distractors": "env.min_distractors",
                 "max_distractors": "env.max_distractors", "max_episode_steps": "env.max_episode_steps",
                 "train_episodes": "data.train_episodes", "depth": "env.depth",
                 "cameras": "env.cameras"}


def own_dataset_differences(config, workdir: str) -> list:
  """[(config field, the dataset's value, the config's)] where the dataset in the run's own data folder
  (config.data.dir empty) was collected otherwise than `config` says; [] when there is none or it agrees, or the
  dataset lies in a shared config.data.dir (`check_existing` refuses that one)."""
  if config.data.dir:
    return []
  state = rlds.load_state(data_lib.dataset_path(config, workdir))
  if state is None:
    return []
  return [(CONFIG_FIELDS.get(key, key), old, new) for key, old, new in
          summary_differences(state["config"], config_summary(config))]


def serves_fewer_cameras(stored: Mapping[str, Any], wanted: Mapping[str, Any]) -> bool:
  """Whether a dataset summarised by `stored` serves a config that reads some of its cameras: the summaries differ
  only in the cameras and every wanted camera is stored (a front + wrist dataset serves a front-only run, which
  reads the same episodes' front frames). Only a complete dataset may: one camera fewer could not finish it."""
  differences = summary_differences(stored, wanted)
  if [key for key, _, _ in differences] != ["cameras"]:
    return False
  _, have, want = differences[0]
  return set(want) <= set(have)


FOREIGN_MARKERS = ("dataset_info.json", "features.json")   # TFDS metadata: a dataset is there


def check_compatible(path: str, summary: Mapping[str, Any]) -> Dict[str, Any]:
  """The stored state of the dataset at `path` (None if none); a dataset of another config is a UserError."""
  state = rlds.load_state(path)
  if state is not None:
    differences = config_differences(state["config"], summary)
    if differences and state["complete"] and serves_fewer_cameras(state["config"], summary):
      return state
    if differences:
      raise UserError(f"{path} holds a dataset of another config ({'; '.join(differences)}); it is left as it "
                      "is: use another --workdir, or set --config.data.dir to another folder.")
  elif any(os.path.exists(os.path.join(path, name)) for name in FOREIGN_MARKERS):
    # roboshape writes the TFDS metadata only after roboshape.json, so metadata without it is not roboshape's
    raise UserError(f"{path} holds a TFDS dataset that roboshape did not write (it has no "
                    f"{data_lib.STATE_FILE}); it is left as it is: set --config.data.dir to another folder.")
  return state


def _check_workdir_task(config, workdir: str) -> None:
  """A run's own data folder (config.data.dir empty) must not hold the dataset of another task."""
  if config.data.dir:
    return  # a shared folder holds one dataset per task side by side
  root = rundir.data_root(config, workdir)
  mine = data_lib.dataset_name(config.task)
  if os.path.isdir(root):
    for name in sorted(os.listdir(root)):
      if name.startswith("roboshape_") and name != mine:
        raise UserError(f"workdir {workdir} holds a dataset of another config (task: {name[len('roboshape_'):]!r} "
                        f"in the dataset, {config.task!r} in the config; {os.path.join(root, name)}). Use another "
                        "--workdir, or set --config.data.dir to share datasets between experiments.")


@contextlib.contextmanager
def _exclusive(path: str) -> Iterator[None]:
  """Holds an exclusive lock on the dataset directory (released by the OS even on SIGKILL)."""
  os.makedirs(path, exist_ok=True)
  with open(os.path.join(path, ".collect.lock"), "a") as f:
    try:
      fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      raise UserError(f"another collection is writing {path} right now; wait for it to finish.") from None
    try:
      yield
    finally:
      fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _is_worker_error(e: BaseException) -> bool:
  """roboshape.sim.SimWorkerError (matched by name: tests drive the collector with pools of their own)."""
  return any(cls.__name__ == "SimWorkerError" for cls in type(e).__mro__)


class _SplitCollector:
  """Collects one split: requests seeds, reorders results by seed, commits shards of successes in seed order."""

  def __init__(self, pool, writer: rlds.DatasetWriter, split: str, progress: bool):
    self.pool, self.writer, self.split = pool, writer, split
    info = writer.state["splits"][split]
    self.target, self.shard_size = info["target"], info["episodes_per_shard"]
    shards = writer.shards(split)
    self.kept = writer.num_episodes(split)
    self.failed = sum(len(s["failed_seeds"]) for s in shards)
    self.cursor = shards[-1]["next_seed"] if shards else info["seed_base"]  # first seed not committed
    self.requested_until = self.cursor
    self.buffer: Dict[int, Any] = {}     # finished seeds >= cursor: episode, or None for a failure
    self.pending, self.pending_failed = [], []
    self.frames = 0
    self.start = time.time()
    self.new_successes = self.new_failures = 0
    self.bar = progress_lib.bar(total=self.target, initial=self.kept, unit="ep", dynamic_ncols=True,
                                disable=not progress, desc=f"collect {writer.task} {split}")

  def run(self) -> Dict[str, Any]:
    try:
      self._collect()
    finally:
      self.bar.close()      # also before an error's one line, which then ends the output
    elapsed = time.time() - self.start
    return {"split": self.split, "episodes": self.kept, "failures": self.failed,
            "new_episodes": self.new_successes, "new_failures": self.new_failures,
            "frames": self.frames, "seconds": elapsed}

  def _collect(self) -> None:
    """Collects until the split holds its target, committing shard by shard."""
    restarts = 0
    while self.kept + len(self.pending) < self.target:
      outstanding = [s for s in range(self.cursor, self.requested_until) if s not in self.buffer]
      if not outstanding:
        # Rounds of at most 16 episodes per worker bound the reorder buffer (a slow seed holds back the commits).
        need = min(self.target - self.kept - len(self.pending), max(64, 16 * getattr(self.pool, "num_envs", 1)))
        outstanding = list(range(self.requested_until, self.requested_until + need))
        self.requested_until += need
      try:
        for episode in self.pool.collect(outstanding):
          self._receive(episode)
      except Exception as e:  # pylint: disable=broad-except
        if not _is_worker_error(e) or restarts >= _MAX_WORKER_RESTARTS:
          raise
        restarts += 1
        tqdm.tqdm.write(f"[collect] a simulator worker died ({str(e).strip().splitlines()[-1:]}); "
                        f"restarting it ({restarts}/{_MAX_WORKER_RESTARTS})")
        self.pool.restart()
        continue
      missing = [s for s in outstanding if s not in self.buffer and s >= self.cursor]
      if missing:
        raise RuntimeError(f"the simulator pool returned no episode for seeds {missing[:5]}")

  def _receive(self, episode: Mapping[str, Any]) -> None:
    seed = int(episode["seed"])
    if seed < self.cursor or seed in self.buffer or seed >= self.requested_until:
      return  # a duplicate (e.g. after a worker restart)
    success = bool(episode["success"])
    broken = data_lib.non_finite(episode) if success else None
    if broken:      # a failed episode is never stored: a simulation that blew up is a failure like any other
      raise UserError(f"the expert's episode of seed {seed} ({self.split} split of {self.writer.path}) has "
                      f"non-finite {broken} (NaN or inf): nothing of it was written, the {self.kept} episodes "
                      "committed before it are kept. The seeds are fixed, so collecting again meets it again: the "
                      "simulator or the expert misbehaves on this seed (reproduce it with "
                      "roboshape.sim on that seed).")
    if not self.writer.has_state:   # resuming a dataset begun before the state was stored
      episode = {k: v for k, v in episode.items() if k != "state"}
    self.buffer[seed] = episode if success else None
    self.frames += int(episode["image"].shape[0])
    self.new_successes += success
    self.new_failures += not success
    self.failed += not success
    rate = (self.kept + len(self.pending) + sum(e is not None for e in self.buffer.values()))
    rate = rate / max(1, rate + self.failed)
    elapsed = max(1e-9, time.time() - self.start)
    self.bar.set_postfix_str(f"{(self.new_successes + self.new_failures) / elapsed:.2f} episodes/s, expert success "
                             f"{100 * rate:.1f}% ({self.failed} failed), {self.frames / elapsed:.0f} frames/s",
                             refresh=False)
    self.bar.update(int(success))
    while self.cursor in self.buffer:
      item = self.buffer.pop(self.cursor)
      if item is None:
        self.pending_failed.append(self.cursor)
      else:
        self.pending.append(item)
      self.cursor += 1
      if len(self.pending) == self.shard_size or self.kept + len(self.pending) == self.target:
        self._commit()

  def _commit(self) -> None:
    try:
      self.writer.add_shard(self.split, self.pending, self.pending_failed, next_seed=self.cursor)
    except Exception as e:  # pylint: disable=broad-except
      if not fileio.disk_full(e):   # OSError(ENOSPC), or a library's error that says the disk is full
        raise
      raise DiskFull(f"{DiskFull.PREFIX} while writing {self.writer.path}: the "
                     f"{self.writer.num_episodes('train')} train and {self.writer.num_episodes('val')} val episodes "
                     "committed so far are kept and readable (roboshape.json says complete: false). Free some space "
                     "and run the same command again to finish.") from None
    self.kept += len(self.pending)
    self.pending, self.pending_failed = [], []


def repair_shards(pool, path: str, state: Mapping[str, Any], progress: bool = True) -> List[str]:
  """Re-collects every recorded shard of the dataset at `path` whose file is missing or differs from its record.

  Each damaged shard is collected again from its recorded seeds with `pool` and written back only when it is byte
  for byte the recorded one (size and sha256): the dataset ends as it was collected. A simulator of another env
  version, or one that gives other episodes, is a UserError that names the shard and says to collect again.
  Returns the repaired shards' file names.
  """
  damaged = rlds.shard_problems(path, state)
  if not damaged:
    return []
  first = os.path.join(path, damaged[0]["file"])
  version = getattr(pool, "env_version", None)
  if state["env_version"] and version and version != state["env_version"]:
    raise UserError(f"shard {first} is {damaged[0]['problem']}, and only the simulator that collected it (env "
                    f"version {state['env_version']!r}, this one is {version!r}) can make it again: run the same "
                    "command with the roboshape of that version (it re-collects the damaged shards and keeps the "
                    f"rest), or collect a new dataset into another --config.data.dir. {path} is left as it is.")
  for item in damaged:
    shard = state["splits"][item["split"]]["shards"][item["index"]]
    if progress:
      print(f"[collect] shard {item['file']} is {item['problem']}: re-collecting its {len(shard['seeds'])} "
            "episode(s) from their recorded seeds", flush=True)
    episodes = _collect_seeds(pool, shard["seeds"], os.path.join(path, item["file"]))
    if not state["config"].get("state", False):   # a dataset begun before the state was stored
      episodes = [{k: v for k, v in e.items() if k != "state"} for e in episodes]
    rlds.rewrite_shard(path, state, item["split"], item["index"], episodes)
  return [item["file"] for item in damaged]


def _collect_seeds(pool, seeds: Sequence[int], file: str) -> List[Dict[str, Any]]:
  """The episodes of `seeds`, in their order, from `pool` (restarting a dead worker like `_SplitCollector`)."""
  got: Dict[int, Any] = {}
  restarts = 0
  while len(got) < len(seeds):
    try:
      for episode in pool.collect([s for s in seeds if s not in got]):
        if int(episode["seed"]) in seeds:
          got[int(episode["seed"])] = episode
    except Exception as e:  # pylint: disable=broad-except
      if not _is_worker_error(e) or restarts >= _MAX_WORKER_RESTARTS:
        raise
      restarts += 1
      pool.restart()
      continue
    missing = [s for s in seeds if s not in got]
    if missing:
      raise RuntimeError(f"the simulator pool returned no episode for seeds {missing[:5]}")
  failed = [s for s in seeds if not bool(got[s]["success"])]
  if failed:
    raise UserError(f"re-collecting the damaged shard {file}: the expert now fails seed(s) {failed[:5]} it "
                    "solved before (the simulator differs from the one that collected it): repair it with the "
                    "roboshape that collected it, or collect a new dataset into another --config.data.dir. "
                    f"{os.path.dirname(file)} is left as it is.")
  return [got[s] for s in seeds]


def collect_dataset(pool, path: str, summary: Mapping[str, Any], targets: Mapping[str, int],
                    progress: bool = True) -> Dict[str, Any]:
  """Collects (or finishes) the dataset at `path` with `pool` (anything with `collect(seeds) -> episodes`).

  Returns a report: per split the episodes kept, expert failures and this run's frames and seconds.
  """
  with _exclusive(path):
    state = check_compatible(path, summary)
    repaired = repair_shards(pool, path, state, progress) if state is not None else []
    if state is not None and state["complete"]:
      return {"complete": True, "already_complete": True, "repaired": repaired}
    version = getattr(pool, "env_version", None)
    if state is not None and state["env_version"] and version and version != state["env_version"]:
      raise UserError(f"{path} was partly collected with env version {state['env_version']!r}, the simulator is "
                      f"now {version!r}: finish it with the roboshape of that version, or collect a new dataset "
                      "into another --config.data.dir. It is left as it is.")
    writer = rlds.DatasetWriter(path, summary, targets, seed_bases=SEED_BASES)
    report = {"complete": False, "already_complete": False, "repaired": repaired}
    for split in data_lib.SPLITS:
      report[split] = _SplitCollector(pool, writer, split, progress).run()
    writer.finish()
    report["complete"] = True
    return report


def _print_report(path: str, report: Mapping[str, Any]) -> None:
  if report.get("repaired"):
    print(f"[collect] re-collected {len(report['repaired'])} damaged shard(s) of {path}; each is again byte for "
          "byte the one recorded", flush=True)
  if report.get("already_complete"):
    if report.get("repaired"):
      print(f"[collect] dataset complete: {path}", flush=True)
    else:
      print(f"[collect] {path} already holds the complete dataset of this config; nothing to do.", flush=True)
    return
  for split in data_lib.SPLITS:
    r = report[split]
    tried = r["episodes"] + r["failures"]
    rate = r["new_episodes"] / max(1e-9, r["seconds"])
    print(f"[collect] {split}: {r['episodes']} episodes kept, {r['failures']} expert failures "
          f"(success {100 * r['episodes'] / max(1, tried):.1f}% of {tried} seeds); this run: {r['new_episodes']} "
          f"episodes, {r['frames']} frames in {r['seconds']:.0f}s ({3600 * rate:.0f} episodes/h)", flush=True)
  print(f"[collect] dataset complete: {path}", flush=True)


def check_existing(config, workdir: str):
  """The stored state of the dataset this config would collect (None if none); UserError when the workdir's data
  folder holds a dataset of another task, or the dataset there was made with another config."""
  _check_workdir_task(config, workdir)
  return check_compatible(data_lib.dataset_path(config, workdir), config_summary(config))


def run(config, workdir: str) -> None:
  """The collect stage: the dataset of config.task at `roboshape.data.dataset_path(config, workdir)`, its
  identity then recorded in the run's <workdir>/dataset.json (`record_dataset`)."""
  path = data_lib.dataset_path(config, workdir)
  summary = config_summary(config)
  state = check_existing(config, workdir)
  if state is not None and state["complete"] and not rlds.shard_problems(path, state):
    _print_report(path, {"already_complete": True})
    record_dataset(path, workdir)
    return
  from roboshape.sim import EnvSpec, SimPool  # pylint: disable=import-outside-toplevel
  spec = EnvSpec.from_config(config, level=LEVEL)
  with SimPool(spec, num_workers=int(config.sim.num_workers)) as pool:
    report = collect_dataset(pool, path, summary, split_targets(config))
  _print_report(path, report)
  record_dataset(path, workdir)


def record_dataset(path: str, workdir: str) -> str:
  """Writes <workdir>/dataset.json, the identity of the dataset at `path` (roboshape.data.record), which the run's
  later stages train on and its published cell carries; returns its path."""
  out = rundir.dataset_record(workdir)
  os.makedirs(workdir, exist_ok=True)
  fileio.atomic_write_json(out, data_lib.record(rlds.load_state(path)), indent=1)
  return out
