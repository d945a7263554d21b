"""The run folder: where each stage of a run writes, and the config it ran with. Every module asks here.

  <workdir>/config.json      the config that ran (`save_config`, `load_config`)
  <workdir>/data/            the datasets (`data_root`: config.data.dir when set), one per task
  <workdir>/dataset.json     the identity of the dataset the run was trained on, wherever it lies (`dataset_record`;
                             written by the collect stage, roboshape/data)
  <workdir>/<encoder>/       a pretrained encoder's: checkpoints/, tb/, val_metrics.json/.png (`pretrain_dir`);
                             savi/ (with figures/) for SAVi, ae/ for the AE (`pretrain_dir`)
  <workdir>/features/<key>/  encoder features cached per (dataset, encoder checkpoint)       (`features_dir`)
  <workdir>/policy/          checkpoints/, tb/, norm_stats.json, encoder.json, summary.json   (`policy_dir`);
                             with policy.train_seeds, one such folder per seed: policy/seed_<s>/; and
                             fingerprint.json, the config fields it was trained with (as <encoder>/ has its own:
                             roboshape/train/fingerprint.py)
  <workdir>/eval/            results.jsonl/.json/.csv, tables, plots, videos/                 (`eval_dir`)
  <workdir>/report/          the report over a grid's runs (or the run itself)                (`report_dir`)

A grid config (configs/reproduce.py) runs each (task, column) in <workdir>/<task>_<column>/ (`grid_run_dir`; a
column is an encoder, alone or with options: roboshape/encoders/columns.py), reading the task's dataset from
<data_root>/<task>; a grid run skipped for bad input leaves SKIPPED.json there. The grid's own stage log
(<workdir>/stages.json) holds one entry, GRID_CLOCK: the wall time the grid process ran, over its restarts. A run
with pretrain.from_workdir set serves the encoder another run's pretrain stage trained, from that run's folders
(`pretrained_workdir`).
`STAGES` names the stages, in the order a config runs them.

Training seeds, one name for every training stage (`train_seeds`): with pretrain.train_seeds = (s1, s2, ...)
(roboshape/train/pretrain.py) the pretrained encoder's folder holds one training run per seed instead, each as
above, and the choice among them:
  <encoder>/seed_<s>/            one seed's checkpoints/, tb/, figures/, val_metrics.json/.png  (`seed_dir`)
  <encoder>/selected.json        every seed's final validation and the selected seed        (`selection_path`)
  <encoder>/seeds_<metric>.png   every seed's validation curve of the selection metric       (`seeds_figure`)
and with policy.train_seeds one policy per seed in policy/seed_<s>/. With seeds = () (the default) there is one
run, with config.seed, in the stage's folder itself.

A config.json written before the pretrain section existed is read through `upgrade_config` (RENAMED). Fields that
left the configs are in REMOVED; a run trained with one of them that today's code cannot load is refused by
`check_no_chunks` where a workdir's policy is loaded or its run resumed.
"""
import contextlib
import copy
import fcntl
import json
import os
from typing import Tuple

from roboshape import fields
from roboshape import fileio
from roboshape.errors import UserError

STAGES = ("collect", "pretrain", "cache", "train_policy", "evaluate", "report")
GRID_CLOCK = "grid"                # the grid workdir's stage log entry: the grid's attempts (roboshape/stages.py)
CONFIG_FILE = "config.json"
SKIPPED_FILE = "SKIPPED.json"      # a grid run skipped for bad input: {"reason": the one-line message}
CHECKPOINTS = "checkpoints"
RESULTS_FILE = "results.json"      # <eval_dir>/results.json: every rollout and the per-level summary
RESULTS_CSV = "results.csv"        # <eval_dir>/results.csv (and a published run's): one row per rollout
RUN_LOCK = ".run.lock"             # <workdir>/.run.lock: held by the run working in the workdir (`hold_workdir`)
SELECTION_FILE = "selected.json"   # <encoder>/selected.json: the seed of pretrain.train_seeds pretraining selected
DATASET_FILE = "dataset.json"      # <workdir>/dataset.json (and a published run's): its dataset's identity
FIGURES_DIR = "figures"            # <encoder>/[seed_<s>/]figures/step_<n>.png: pretraining's validation figures
FINGERPRINT_FILE = "fingerprint.json"   # <encoder>/ and policy/: the config fields that stage's output was made with

# Fields that moved, old dotted name -> new: the pretraining settings SAVi and the AE share left the savi section.
RENAMED = {
    **{f"savi.train.{f}": f"pretrain.train.{f}" for f in (
        "steps", "batch_size", "clip_length", "learning_rate", "warmup_steps", "clip_norm", "depth_weight",
        "checkpoint_every", "keep_checkpoints", "log_every")},
    "savi.train.seeds": "pretrain.train_seeds",
    **{f"savi.eval.{f}": f"pretrain.eval.{f}" for f in ("every", "episodes", "frames")},
}
# Fields that left the configs, old dotted name -> (the default it had, why it left). A command line that sets one
# is refused in one line saying why (roboshape/cli.py); an old run's config.json keeps it, roboshape/study.py counts
# it as a change only where it differs from that default, and the evaluation's policy fingerprint hashes the
# policy.eval ones at it (roboshape/eval/closed_loop.py), so old evaluation logs still resume.
_CHUNKING = "action chunking lost its comparison (results/small/recipe/README.md)"
REMOVED = {
    "policy.chunk": (1, _CHUNKING),
    "policy.eval.ensemble_decay": (0.01, _CHUNKING),
}
# Fields added to the configs after runs were saved, dotted name -> the value a run saved before the field existed
# ran with (the behaviour the code had then, which today's default for the field need not be). `load_config` reads
# every config.json through this table, so code reads today's fields of any run's config without defaults of its
# own, and a fingerprint record lacking one compares as that value (roboshape/train/fingerprint.py). A field added
# to configs/common.py gets its entry here; tests/test_launch.py reads the published configs back through it.
ADDED = {
    "env.depth": False,
    "env.cameras": ("front",),           # the front camera alone (roboshape/envs/camera.py DEFAULT)
    "pretrain.train.depth_weight": 0.0,
    "pretrain.train.mask_weight": 0.0,
    "pretrain.train_seeds": (),
    "pretrain.from_workdir": "",
    "savi.pool": 1,
    "savi.full_grid": 0,
    "savi.init_mean": "shared",
    "savi.slot_gradient": "full",
    "savi.predictor.identity_init": False,
    "savi.decoder.rgb": "spatial",
    "savi.decoder.position": "coords",
    "state.withhold": (),
    "state.relative": True,
    "policy.proprio": False,
    "policy.hand_relative": False,
    "policy.frame_pool": False,
    "policy.train.change_weight": 1.0,
    "policy.train_seeds": (),
}
# The AE's fields that were read from the savi section before the AE had its own (its ae section's defaults).
_AE_FROM_SAVI = ("pool", "encoder", "decoder.grid_size", "decoder.features", "decoder.kernel_size",
                 "decoder.strides", "decoder.upsampling", "decoder.position")


def config_path(workdir: str) -> str:
  return os.path.join(workdir, CONFIG_FILE)


def save_config(config, workdir: str) -> str:
  """Writes config.json into the workdir (atomically) and returns its path."""
  path = config_path(workdir)
  try:
    os.makedirs(workdir, exist_ok=True)
    fileio.atomic_write_text(path, config.to_json_best_effort(indent=2, sort_keys=True))
  except OSError as e:
    raise UserError(f"cannot write {path} ({e.strerror or e}); give a --workdir you can write to.") from None
  return path


def load_config(workdir: str):
  """The config a run saved in its workdir, as a ConfigDict."""
  import ml_collections  # pylint: disable=import-outside-toplevel
  path = config_path(workdir)
  if not os.path.exists(path):
    raise UserError(f"{path} not found: is {workdir!r} the workdir of a `python launch.py` run?")
  try:
    with open(path, encoding="utf-8") as f:
      data = json.load(f)
  except (OSError, ValueError) as e:        # unreadable, not UTF-8, not JSON
    raise UserError(f"{path} is damaged ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}): it is "
                    "the record of the config that ran; restore it (e.g. from a copy or the results it was "
                    "published with) rather than deleting the run.") from None
  if not isinstance(data, dict):
    raise UserError(f"{path} is damaged (a JSON {type(data).__name__}, not a config): restore it rather than "
                    "deleting the run.")
  return ml_collections.ConfigDict(upgrade_config(data))


def check_no_chunks(config, workdir: str) -> None:
  """Raises a one-line UserError when `config` (the config.json of the run in `workdir`, a dict or a ConfigDict)
  was trained with action chunks (policy.chunk > 1): today's policy predicts one action a step, so that run's
  checkpoints do not fit it. A policy.chunk of 1, or none, is today's policy."""
  chunk = (config.get("policy") or {}).get("chunk", 1)
  if chunk != 1:
    raise UserError(f"{config_path(workdir)} is a run trained with action chunks (policy.chunk={chunk}), which this "
                    f"roboshape no longer has: {_CHUNKING}; load it with the roboshape commit it was trained with "
                    "(nothing in it was changed).")


def upgrade_config(data: dict) -> dict:
  """A config.json's dict in today's fields: one written before the pretrain section existed has its pretraining
  settings moved there (RENAMED) and its clip stated on the mean loss (as it was then:
  pretrain.train.clip_norm_of); one written before the AE had its own section gets it as the AE read it then, the
  savi section's frame encoder, decoder and pool; and every field of ADDED it lacks reads the value such runs ran
  with. The dict given is left as it was."""
  data = copy.deepcopy(data)
  if "pretrain" not in data and "savi" in data:
    for old, new in RENAMED.items():
      parent, _, leaf = old.rpartition(".")
      node = fields.get(data, parent, {})
      if leaf in node:
        fields.put(data, new, node.pop(leaf), create=True)
    if not data["savi"].get("train", True):
      del data["savi"]["train"]            # every field of it moved
    fields.put(data, "pretrain.train.clip_norm_of", "mean", create=True)
    if "ae" in data:                       # the AE read these from the savi section, whatever its own said
      _ae_from_savi(data)
  if "savi" in data and "task" in data and "ae" not in data:
    _ae_from_savi(data)
    data["ae"]["latent_size"] = 0          # 0: savi.slot_size, the only width there was
  for field in predates(data):
    fields.put(data, field, ADDED[field], create=True)
  return data


def _ae_from_savi(data: dict) -> None:
  for field in _AE_FROM_SAVI:
    value = fields.get(data["savi"], field, None)
    if value is not None:
      fields.put(data, f"ae.{field}", json.loads(json.dumps(value)), create=True)


def predates(data: dict) -> Tuple[str, ...]:
  """The fields of ADDED that a saved config's dict lacks: those added to the configs after it was written."""
  return tuple(f for f in ADDED if fields.get(data, f, _MISSING) is _MISSING)


_MISSING = object()


def data_root(config, workdir: str) -> str:
  """The folder that holds the datasets of a run: config.data.dir, or <workdir>/data when it is empty."""
  return config.data.dir or os.path.join(workdir, "data")


def dataset_record(workdir: str) -> str:
  """<workdir>/dataset.json: the identity of the dataset the run was trained on (roboshape.data.record)."""
  return os.path.join(workdir, DATASET_FILE)


def pretrained_workdir(config, workdir: str) -> str:
  """The workdir whose pretrain stage trained the run's encoder: the run's own, or the one its
  pretrain.from_workdir names (another run of the same task and encoder, e.g. a grid's plain column, whose SAVi or
  AE a column with policy options serves). A config.json without the field is the run's own."""
  return (config.get("pretrain") or {}).get("from_workdir", "") or workdir


def pretrain_dir(workdir: str, encoder: str) -> str:
  """The folder of an encoder's pretrain stage, named after the encoder (savi/, ae/; absent for one without)."""
  return os.path.join(workdir, encoder)


def seed_dir(stage_dir: str, seed=None) -> str:
  """The training run of one seed of `train_seeds` inside a training stage's folder (pretrain_dir, policy/):
  <stage_dir>/seed_<s>/, or stage_dir itself for seed None (a stage without seeds)."""
  return stage_dir if seed is None else os.path.join(stage_dir, f"seed_{int(seed)}")


def selection_path(stage_dir: str) -> str:
  """<stage_dir>/selected.json: which seed of pretrain.train_seeds the pretrain stage selected (`load_selection`)."""
  return os.path.join(stage_dir, SELECTION_FILE)


def load_selection(stage_dir: str):
  """The dict <stage_dir>/selected.json holds ({"selected_seed", "metric", "seeds": [{"seed", "step", <metric>...}],
  ...}, written by roboshape/train/pretrain.py), or None when there is none (seeds not trained to the end yet)."""
  path = selection_path(stage_dir)
  if not os.path.exists(path):
    return None
  try:
    with open(path) as f:
      selection = json.load(f)
    seeds = [int(s["seed"]) for s in selection["seeds"]]
    if int(selection["selected_seed"]) not in seeds:
      raise ValueError(f"selected_seed {selection['selected_seed']} is not one of {seeds}")
  except (OSError, ValueError, KeyError, TypeError) as e:
    raise UserError(f"{path} is not a readable seed selection ({e}); run the pretrain stage again to rewrite it.") \
        from None
  return selection


def seeds_figure(stage_dir: str, metric: str) -> str:
  """<stage_dir>/seeds_<metric>.png: every seed's validation curve of the selection metric, overlaid."""
  return os.path.join(stage_dir, f"seeds_{metric}.png")


def fingerprint_path(stage_dir: str) -> str:
  """<stage_dir>/fingerprint.json: the config fields the stage that writes `stage_dir` read, with their values."""
  return os.path.join(stage_dir, FINGERPRINT_FILE)


def features_root(workdir: str) -> str:
  """<workdir>/features/: every feature cache of the run (`features_dir`)."""
  return os.path.join(workdir, "features")


def features_dir(workdir: str, key: str) -> str:
  """The feature cache of one (encoder, dataset, dtype), named by its key (roboshape/train/cache.py)."""
  return os.path.join(features_root(workdir), key)


def policy_dir(workdir: str, train_seed=None) -> str:
  """<workdir>/policy/, or <workdir>/policy/seed_<s>/ for training seed s of `policy.train_seeds`."""
  return seed_dir(os.path.join(workdir, "policy"), train_seed)


def train_seeds(config, stage: str = "policy") -> tuple:
  """The training seeds of a training stage's runs, config.<stage>.train_seeds (stage "policy" or "pretrain"), or
  (None,) when it is empty: one run, trained with config.seed, in the stage's folder itself (`seed_dir`)."""
  return tuple(int(s) for s in config[stage].get("train_seeds", ())) or (None,)


def eval_dir(workdir: str) -> str:
  return os.path.join(workdir, "eval")


def rollout_log(workdir: str, train_seed=None) -> str:
  """<workdir>/eval/results.jsonl, the rollout log of the run's policy, or results_seed_<s>.jsonl for training seed s
  of `policy.train_seeds`: one line per finished rollout."""
  name = "results.jsonl" if train_seed is None else f"results_seed_{int(train_seed)}.jsonl"
  return os.path.join(eval_dir(workdir), name)


def videos_dir(workdir: str) -> str:
  return os.path.join(eval_dir(workdir), "videos")


def report_dir(workdir: str) -> str:
  return os.path.join(workdir, "report")


def checkpoints(stage_dir: str) -> str:
  """The orbax checkpoints of a training stage's folder (pretrain_dir, policy_dir)."""
  return os.path.join(stage_dir, CHECKPOINTS)


def saved_steps(stage_dir: str) -> list:
  """The steps of a training stage's folder's checkpoints as their folders name them, oldest first (none when there
  are none): a quick reading for progress reports, not a check that they restore (roboshape/checkpoint.py)."""
  try:
    names = os.listdir(checkpoints(stage_dir))
  except OSError:
    return []
  return sorted(int(n) for n in names if n.isdigit())


def grid_cell(task: str, column: str) -> str:
  """A grid cell's name, "<task>_<column>" (a column: an encoder, e.g. "savi", or an encoder with options,
  "savi+proprio"): its run's folder under the grid's workdir, its published folder, a name in grid.skip."""
  return f"{task}_{column}"


def grid_run_dir(workdir: str, task: str, column: str) -> str:
  """The workdir of one run of a grid: <workdir>/<task>_<column>/ (grid_cell)."""
  return os.path.join(workdir, grid_cell(task, column))


def grid_data_dir(config, workdir: str, task: str, other_cameras=()) -> str:
  """The data.dir of a grid's runs of `task` that see the front camera and `other_cameras` (roboshape.envs.camera
  `others`): the task's datasets, shared by those runs and collected once; <data root>/<task> for the front camera
  alone, <task>_<other cameras> with more ("pick_wrist")."""
  return os.path.join(data_root(config, workdir), "_".join([task, *other_cameras]))


# ----------------------------------------------------------------------------------------------------------------
# The stage log: <workdir>/stages.json, what each stage of a run did and how long it took (`roboshape.status`).

STAGE_LOG = "stages.json"


def stage_log_path(workdir: str) -> str:
  return os.path.join(workdir, STAGE_LOG)


def read_stage_log(workdir: str, strict: bool = False) -> dict:
  """{stage: {state: "running" | "done", pid, started, finished, seconds, core_seconds, cores}} of a run ({} when
  none ran yet).

  `started` is its first attempt's start, `seconds` the wall time of the stage's attempts, summed over resumes;
  `core_seconds` the same, each attempt's wall time times the cores it held (`cores`: its process's CPU affinity, so
  a grid lane's one core, a collection's whole machine). An attempt that never finished (killed with its session) counts up to its last beat
  (`stage_clock`) once the next attempt starts. A damaged log reads as {} (a run starts it afresh: it records
  times, not results), or with `strict` (the tools that report it) is a UserError naming the file."""
  path = stage_log_path(workdir)
  if not os.path.exists(path):
    return {}
  try:
    with open(path, encoding="utf-8") as f:
      log = json.load(f)
  except (OSError, ValueError) as e:
    log = e
  if isinstance(log, dict):
    return log
  if strict:
    raise UserError(f"{path} is damaged (not a JSON object of stages): the stage times it held are lost, the "
                    "run's results are not; the next `python launch.py` on this workdir starts it again.")
  return {}


def logged_time(entry: dict) -> Tuple[float, float]:
  """(wall seconds, core-seconds) an entry of the stage log accounts for: its finished attempts and the unfinished
  ones the next attempt added, plus an attempt still open (running, or killed) up to its last beat. An entry logged
  before cores were recorded counts one core."""
  seconds = float(entry.get("seconds", 0.0))
  core = float(entry.get("core_seconds", seconds))
  if entry.get("state") == "running" and "beat" in entry and "attempt" in entry:
    open_for = max(0.0, float(entry["beat"]) - float(entry["attempt"]))
    seconds, core = seconds + open_for, core + open_for * int(entry.get("cores", 1))
  return seconds, core


def _held_cores() -> int:
  return len(os.sched_getaffinity(0))


def record_stage(workdir: str, stage: str, state: str, seconds: float = 0.0) -> None:
  """Notes in the stage log that `stage` is now "running" (in this process) or "done" after `seconds` more.

  Starting an attempt first adds the time of the one before it when that one never finished: its wall time up to
  its last beat (`beat_stage`)."""
  import datetime  # pylint: disable=import-outside-toplevel
  import time  # pylint: disable=import-outside-toplevel
  log = read_stage_log(workdir)
  entry = dict(log.get(stage, {}))
  now = datetime.datetime.now().isoformat(timespec="seconds")
  if state == "running":
    seconds, core = logged_time(entry)              # with the attempt before this one, if it never finished
    entry.update(seconds=round(seconds, 1), core_seconds=round(core, 1))
    clock = time.time()
    entry.update(state="running", pid=os.getpid(), started=entry.get("started", now), cores=_held_cores(),
                 attempt=clock, beat=clock)
  else:
    before, core = logged_time(dict(entry, state="done"))
    entry.update(state="done", finished=now, seconds=round(before + seconds, 1),
                 core_seconds=round(core + seconds * int(entry.get("cores", _held_cores())), 1))
    for key in ("pid", "attempt", "beat"):
      entry.pop(key, None)
  log[stage] = entry
  os.makedirs(workdir, exist_ok=True)
  fileio.atomic_write_json(stage_log_path(workdir), log)


def beat_stage(workdir: str, stage: str) -> None:
  """Notes that this process's attempt at `stage` is still running now (what a killed attempt is counted up to)."""
  import time  # pylint: disable=import-outside-toplevel
  log = read_stage_log(workdir)
  entry = log.get(stage)
  if isinstance(entry, dict) and entry.get("state") == "running" and entry.get("pid") == os.getpid():
    entry["beat"] = time.time()
    fileio.atomic_write_json(stage_log_path(workdir), log)


@contextlib.contextmanager
def stage_clock(workdir: str, stage: str, every: float = 60.0):
  """Logs one attempt at `stage` around the block: "running" at its start, a beat every `every` seconds from a
  background thread (so a killed attempt's time is not lost), a last beat when the block raises (an interrupted
  attempt; the next one adds its time), "done" with its wall time when it ends well."""
  import threading  # pylint: disable=import-outside-toplevel
  import time  # pylint: disable=import-outside-toplevel
  record_stage(workdir, stage, "running")
  start, stop = time.time(), threading.Event()

  def beat():
    while not stop.wait(every):
      try:
        beat_stage(workdir, stage)
      except OSError:       # a full disk: the stage itself meets it and says so
        pass

  thread = threading.Thread(target=beat, name=f"stage-clock-{stage}", daemon=True)
  thread.start()
  ended_well = False
  try:
    yield
    ended_well = True
  finally:
    stop.set()
    thread.join()
    if ended_well:
      record_stage(workdir, stage, "done", time.time() - start)
    else:
      with contextlib.suppress(OSError):
        beat_stage(workdir, stage)


# ----------------------------------------------------------------------------------------------------------------
# One run per workdir.

@contextlib.contextmanager
def hold_workdir(workdir: str):
  """Holds <workdir>/.run.lock for the body: an exclusive flock, which the operating system releases when the
  holder dies however it dies (a killed run never blocks the next one). The file holds the holder's pid. A second
  run on a held workdir gets a UserError naming that pid, before it writes anything else: two runs on one workdir
  would train, evaluate and log into the same files."""
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, RUN_LOCK)
  with open(path, "a+") as f:
    try:
      fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      f.seek(0)
      holder = f.read().strip() or "unknown"
      raise UserError(f"{workdir} is in use by another run (pid {holder}): wait for it to end, or stop that run "
                      "first; two runs on one workdir would write the same files.") from None
    f.seek(0)
    f.truncate()
    f.write(f"{os.getpid()}\n")
    f.flush()
    try:
      yield
    finally:
      fcntl.flock(f.fileno(), fcntl.LOCK_UN)
