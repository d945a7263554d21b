"""The `evaluate` stage: closed-loop rollouts of the trained policy under each generalization level.

For each level in `config.eval.levels`, S = `config.eval.num_seeds` evaluation seeds x R =
`config.eval.rollouts_per_seed` rollouts. The simulator runs in the bridge's pool (worker processes, one env each,
whatever the physics backend); the policy runs in this process, batched over the pool's envs. With
`policy.train_seeds` every training seed's policy plays the same rollouts (videos of the first one only).

Seed scheme. Rollout r of evaluation seed s gets the env seed

  config.eval.seed_offset + s * 100_000 + r          (seed_offset = 1_000_000_000 by default)

the same at every level (so levels are compared on the same layouts, only what the level changes differs). The
training and validation demos use small seeds (< 10^8), so evaluation layouts are never training layouts.

Rollouts run in waves of `pool.num_envs`: the pool resets the envs of a wave together (`pool.reset(seeds)`), the
policy's history is cleared for those slots (`policy.reset_slots`), and the wave is stepped until every episode is
done (success or horizon; a done env is a no-op in the pool). A finished rollout is appended to
<workdir>/eval/results.jsonl at once, so a crash keeps it and a rerun skips it. A simulator worker that dies
(`SimWorkerError`) is replaced (`pool.restart()`) and the wave's unfinished rollouts are re-run, up to
`config.eval.max_retries` times each, alone in their wave so that a rollout that kills its worker cannot sink
the others; past that the rollout is recorded as ended "worker_crash" and left out of
the statistics (tables say how many). Actions are clipped to [-1, 1] before they reach the env.

Where a failure is lost, per rollout (from the pool's privileged `state`, which the policy need not read):
`closest_cube_cm`, the tool centre point's closest distance to the cube over the episode, in centimetres (a policy
that never reaches the cube against one that reaches it and fails to grasp), and `first_move`, the mean length of
the position part of the policy's first FIRST_STEPS actions (controller units, each axis at most 1): a policy that
imitates the motion it sees in its history starts still (the copycat failure), where the experts start at full speed.

Outputs in <workdir>/eval/: results.jsonl (the log), results.json (every rollout + per-level summary), results.csv,
table.md, table.tex, success_by_level.png, videos/<level>_s<seed>.{mp4,gif} for the first
`config.eval.videos_per_level` rollouts of each level, and for SAVi videos/<...>_slots.{mp4,gif}: the camera frame,
SAVi's reconstruction and every slot beside it (roboshape.eval.videos.SaviSlotVideo, the paper's Figure 8).
Videos are written under a temporary name and renamed, so a kill leaves none half-written; a resumed evaluation
re-runs the logged rollouts whose planned video is missing, to record it (their logged results stand).
Each rollout's `encoder` field, and the tables', is the run's column (roboshape/encoders/columns.py): its encoder
with the options its config turns on ("savi+proprio"), so runs that differ by an option are told apart.
"""
import collections
import dataclasses
import hashlib
import json
import os
import shutil
import time
from typing import Callable, Dict, Iterable, List, Optional, Sequence

import numpy as np
from tqdm import tqdm

from roboshape import envs
from roboshape import fileio
from roboshape import progress
from roboshape import ranges
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.envs import camera as camera_lib
from roboshape.envs import state as state_lib
from roboshape.envs.palettes import LEVEL_NAMES
from roboshape.errors import UserError
from roboshape.report import plots
from roboshape.report import results as results_lib
from roboshape.report import tables
from roboshape.eval import videos
from roboshape.sim.spec import CAMERA_KEYS
from roboshape.sim.spec import MAX_SEED

SEED_STRIDE = 100_000
FIRST_STEPS = 5     # the actions `first_move` averages over

# The ranges of the eval section (its levels and seeds are checked together by check_config).
RANGES = (
    ranges.Int("eval.num_seeds", 1, "evaluation seeds per level"),
    ranges.Int("eval.rollouts_per_seed", 1, "rollouts per evaluation seed"),
    ranges.Int("eval.seed_offset", 0, "the first evaluation env seed"),
    ranges.Int("eval.max_retries", 0, "re-runs of a rollout whose simulator worker died"),
    ranges.Int("eval.videos_per_level", 0, "rollouts recorded as videos per level"),
    ranges.Int("eval.video_fps", 1, "frames per second of the videos"),
)


def check_config(config) -> None:
  """Raises UserError for the first bad field of the evaluation plan: known levels, RANGES, and env seeds that stay
  within one evaluation seed's stride and the simulator's range (roboshape/config_check.py runs it before any
  stage)."""
  levels = ranges.value(config, "eval.levels")
  if (isinstance(levels, str) or not isinstance(levels, (tuple, list)) or not levels
      or any(l not in LEVEL_NAMES for l in levels)):
    raise UserError(f"eval.levels={levels!r}: use a non-empty tuple of the levels "
                    f"{ranges.choices(LEVEL_NAMES)}, e.g. \"('train', 'L1')\".")
  ranges.check(config, RANGES)
  ev = config.eval
  if ev.rollouts_per_seed > SEED_STRIDE:
    raise UserError(f"eval.rollouts_per_seed={ev.rollouts_per_seed}: use at most {SEED_STRIDE} "
                    "(rollouts of one seed must not reach the next seed's env seeds).")
  last = ev.seed_offset + (ev.num_seeds - 1) * SEED_STRIDE + ev.rollouts_per_seed - 1
  if last > MAX_SEED:
    raise UserError(f"eval.seed_offset={ev.seed_offset} with eval.num_seeds={ev.num_seeds} reaches env seed {last}"
                    f", past the largest, {MAX_SEED}: lower eval.seed_offset or eval.num_seeds.")


@dataclasses.dataclass(frozen=True)
class Rollout:
  """One planned rollout: its level, evaluation-seed index, index within that seed, and env seed."""
  level: str
  seed_index: int
  rollout: int
  seed: int


def rollout_plan(levels: Sequence[str], num_seeds: int, rollouts_per_seed: int,
                 seed_offset: int = 1_000_000_000) -> List[Rollout]:
  """Every rollout of an evaluation, level by level, in a fixed order (see the module docstring's seed scheme)."""
  bad = [l for l in levels if l not in LEVEL_NAMES]
  if bad:
    raise UserError(f"unknown evaluation level(s) {bad}; config.eval.levels takes {', '.join(LEVEL_NAMES)}.")
  if not 0 < rollouts_per_seed <= SEED_STRIDE:
    raise UserError(f"config.eval.rollouts_per_seed={rollouts_per_seed}: use 1..{SEED_STRIDE}.")
  if num_seeds < 1:
    raise UserError(f"config.eval.num_seeds={num_seeds}: use 1 or more.")
  return [Rollout(level, s, r, seed_offset + s * SEED_STRIDE + r)
          for level in levels for s in range(num_seeds) for r in range(rollouts_per_seed)]


# on_done(rollout, result dict(success, length, ended), frames uint8 [T+1, H, W, 3] or None; with several cameras
# their views side by side, _views)
OnDone = Callable[[Rollout, Dict, Optional[np.ndarray]], None]


def run_rollouts(pool, policy, rollouts: Sequence[Rollout], on_done: OnDone, record: Iterable[Rollout] = (),
                 max_retries: int = 2, worker_error=Exception, desc: str = "rollouts", initial=(0, 0)) -> None:
  """Rolls `policy` out in `pool` for every rollout; calls `on_done` as each one ends.

  Args:
    pool: has `num_envs`, `reset(seeds, render)` and `step(actions [N,7])`, both -> dict(image uint8 [N,H,W,3], the
      other observation keys the policy reads, success, done, elapsed), and `restart()` (the sim bridge's pool, or
      a fake in tests). `render` says per env whether its camera is rendered: always for a policy that reads one
      of the camera's keys, else (a `state` policy) only for the recorded rollouts, so the others pay no rendering.
    policy: has `reset(batch_size)`, `reset_slots(indices, seeds)` (seeds: the rollouts' env seeds, which key
      a sampling policy's draws), `act_batch(obs) -> [B,7]` (obs: a dict of the keys
      in `policy.inputs`, default ("image",)); it always sees a full batch of `pool.num_envs` observations (a
      short last wave is padded with zeros).
    rollouts: what to run.
    on_done: called once per rollout with its result and, for rollouts in `record`, its frames.
    record: rollouts whose frames to keep for videos.
    max_retries: how many times a rollout whose worker died is re-run before it is reported as "worker_crash".
    worker_error: the exception a dead worker raises (`roboshape.sim.SimWorkerError`).
    desc, initial: the progress bar's label and the (done, successes) it starts from.
  """
  n = int(pool.num_envs)
  record = set(record)
  queue = collections.deque(rollouts)
  retries = collections.Counter()
  policy.reset(batch_size=n)
  stats = {"done": initial[0], "success": initial[1]}
  bar = progress.bar(total=initial[0] + len(queue), initial=initial[0], desc=desc, unit="rollout", dynamic_ncols=True)

  def finish(r, result, frames):
    on_done(r, result, frames)
    if result["ended"] != "worker_crash":
      stats["done"] += 1
      stats["success"] += int(result["success"])
    bar.update(1)
    if stats["done"]:
      bar.set_postfix_str(f"success {stats['success'] / stats['done']:.2f} ({stats['success']}/{stats['done']})")

  try:
    while queue:
      if retries[queue[0]]:
        wave = [queue.popleft()]    # a rollout that saw a crash re-runs alone, so a culprit can't sink others
      else:
        wave = []
        while queue and len(wave) < n and not retries[queue[0]]:
          wave.append(queue.popleft())
      finished = set()
      try:
        _run_wave(pool, policy, wave, n, record, finished, finish)
      except worker_error as e:  # pylint: disable=broad-except
        lines = [l.strip() for l in str(e).strip().splitlines() if l.strip()] or [type(e).__name__]
        first = lines[0] if len(lines) == 1 else f"{lines[0]} ... {lines[-1]}"
        tqdm.write(f"[roboshape] simulator worker died ({first}); restarting it and re-running "
                   f"{len(wave) - len(finished)} unfinished rollout(s)")
        pool.restart()
        for r in reversed([r for r in wave if r not in finished]):
          retries[r] += 1
          if retries[r] > max_retries:
            tqdm.write(f"[roboshape] rollout {r.level}/seed {r.seed} lost its worker {retries[r]} times: "
                       "reported as worker_crash")
            finish(r, dict(success=False, length=0, ended="worker_crash"), None)
          else:
            queue.appendleft(r)
  finally:
    bar.close()


def _run_wave(pool, policy, wave: List[Rollout], n: int, record: set, finished: set, finish) -> None:
  """Resets the wave's envs, steps them until all are done, reports each rollout as it ends."""
  k = len(wave)
  inputs = tuple(getattr(policy, "inputs", ("image",)))
  camera = any(key in CAMERA_KEYS for key in inputs)  # else only the recorded rollouts are rendered
  out = pool.reset([r.seed for r in wave], render=[camera or r in record for r in wave])
  names = tuple(getattr(pool, "milestones", ()))
  policy.reset_slots(list(range(n)), seeds=[r.seed for r in wave] + list(range(k, n)))  # padding: its index
  frames = {i: [_views(out, i)] for i, r in enumerate(wave) if r in record}
  active = np.ones(k, bool)
  closest = _cube_distance(out, k)
  moves = []
  while active.any():
    batch = {key: _pad(np.asarray(out[key]), n) for key in inputs}
    actions = np.clip(np.asarray(policy.act_batch(batch), np.float32)[:k], -1.0, 1.0)
    if len(moves) < FIRST_STEPS:
      moves.append(np.linalg.norm(actions[:, :3], axis=-1))
    out = pool.step(actions)
    if closest is not None:
      closest = np.where(active, np.minimum(closest, _cube_distance(out, k)), closest)
    for i in np.flatnonzero(active):
      if i in frames:
        frames[i].append(_views(out, i))
      if bool(out["done"][i]):
        active[i] = False
        success = bool(out["success"][i])
        finished.add(wave[i])
        result = dict(success=success, length=int(out["elapsed"][i]), ended="success" if success else "horizon")
        if names and "reached" in out:
          result["reached"] = [name for name, hit in zip(names, out["reached"][i]) if hit]
        if closest is not None:
          result["closest_cube_cm"] = round(100.0 * float(closest[i]), 2)
        result["first_move"] = round(float(np.mean([m[i] for m in moves])), 4)
        finish(wave[i], result, np.stack(frames[i]) if i in frames else None)


def _views(out: Dict, i: int) -> np.ndarray:
  """The frame a video of env i shows: every camera's image in `out` side by side, the front one first (the front
  image alone with one camera)."""
  images = [out[camera_lib.keys(c)[0]][i] for c in camera_lib.stored(out)]
  return images[0] if len(images) == 1 else videos.side_by_side([image[None] for image in images])[0]


def _cube_distance(out: Dict, k: int) -> Optional[np.ndarray]:
  """float [k]: the tool centre point's distance to the cube (metres) in each env of `out`, from its privileged
  `state` (roboshape/envs/state.py); None when the pool gives no state (a fake in tests)."""
  if "state" not in out:
    return None
  state = np.asarray(out["state"], np.float32)[:k]
  cuts = state_lib.slices()
  return np.linalg.norm(state[:, cuts["tcp_pos"]] - state[:, cuts["cube_pos"]], axis=-1)


def _pad(x: np.ndarray, n: int) -> np.ndarray:
  """x [k, ...] padded with zeros to [n, ...] (a short last wave)."""
  return x if len(x) == n else np.concatenate([x, np.zeros((n - len(x),) + x.shape[1:], x.dtype)])


# The control settings removed from the configs (rundir.REMOVED) at the defaults they had, hashed along with
# today's (`policy_fingerprint`), so that an evaluation log written while they existed still resumes.
_REMOVED_CONTROL = {k.rsplit(".", 1)[1]: default for k, (default, _) in rundir.REMOVED.items()
                    if k.startswith("policy.eval.")}


def policy_fingerprint(workdir: str, train_seed=None, control=None) -> str:
  """Identifies the trained policy (its checkpoint steps and their times) and how it is run (`control`, the
  config.policy.eval settings: history, action read-out): results of another policy, or of the same one run
  otherwise, are stale."""
  ckpt = rundir.checkpoints(rundir.policy_dir(workdir, train_seed))
  entries = sorted(os.listdir(ckpt)) if os.path.isdir(ckpt) else []
  text = ";".join(f"{e}:{int(os.path.getmtime(os.path.join(ckpt, e)))}" for e in entries)
  if control:
    text += ";" + json.dumps({**_REMOVED_CONTROL, **dict(control)}, sort_keys=True)
  return hashlib.sha1(text.encode()).hexdigest()[:12]


def _slot_video_fn(config, workdir):
  """The SAVi slot-decomposition video maker (frames -> frames), for encoders registered with slot videos only, and
  with one camera (a recorded frame of several holds every view side by side, _views)."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  if not encoders.get(config.encoder).slot_videos or len(config.env.cameras) > 1:
    return None
  return videos.SaviSlotVideo(workdir)


def write_outputs(config, workdir: str, records: Sequence[Dict]) -> Dict[str, str]:
  """results.json, results.csv, table.md, table.tex, success_by_level.png and, when the rollouts recorded the
  task's milestones, milestones.md (how far they got: roboshape.envs.MILESTONES) from the rollout records."""
  out_dir = rundir.eval_dir(workdir)
  os.makedirs(out_dir, exist_ok=True)
  levels = [l for l in LEVEL_NAMES if l in tuple(config.eval.levels)]
  column = columns.of_config(config)     # rollouts logged before runs were labelled by column get it too
  records = sorted((dict(r, encoder=column) for r in records),
                   key=lambda r: (levels.index(r["level"]) if r["level"] in levels else 99, r["seed_index"],
                                  r["rollout"]))
  summary = results_lib.summarize(records)
  paths = dict(json=os.path.join(out_dir, rundir.RESULTS_FILE), csv=os.path.join(out_dir, rundir.RESULTS_CSV),
               md=os.path.join(out_dir, "table.md"), tex=os.path.join(out_dir, "table.tex"),
               png=os.path.join(out_dir, "success_by_level.png"))
  fileio.atomic_write_json(paths["json"], dict(
      task=config.task, encoder=column, levels=levels, num_seeds=config.eval.num_seeds,
      rollouts_per_seed=config.eval.rollouts_per_seed,
      seed_scheme=f"env seed = {config.eval.seed_offset} + seed_index * {SEED_STRIDE} + rollout",
      summary=summary, rollouts=[{k: v for k, v in r.items()} for r in records]), indent=1)
  results_lib.write_csv(paths["csv"], records)
  cells = tables.cells_from_summary(summary, config.task)
  encoders = [column]
  fileio.atomic_write_text(paths["md"], (
      f"### {config.task}: success rate, {tables.encoder_name(column)}\n\n"
      + tables.render_markdown(cells, encoders, levels)
      + "\n" + notes(summary, config.eval.num_seeds, config.eval.rollouts_per_seed) + "\n"))
  fileio.atomic_write_text(paths["tex"], tables.render_latex(
      cells, encoders, levels=levels, label=f"tab:{config.task}_{column}",
      caption=f"Success rate of \\textit{{{config.task}}} over the generalization scenarios "
              f"(mean $\\pm$ std over {_over(summary, config)})"))
  plots.overall_bar_chart(summary, paths["png"], levels=levels,
                          title=f"{config.task}: success rate per level")
  names = envs.MILESTONES[config.task]
  counts = results_lib.milestone_counts(records, names)
  if counts:
    paths["milestones"] = os.path.join(out_dir, "milestones.md")
    fileio.atomic_write_text(paths["milestones"], (
        f"### {config.task}: how far the rollouts got, {tables.encoder_name(column)}\n\n"
        + tables.render_milestones(counts, names)
        + f"\nShare of rollouts that reached each milestone at some step (pooled over seeds), then the same over the "
          f"failed rollouts alone; milestones of {config.task}: {', '.join(names)} (roboshape/envs/tasks.py).\n"))
  return paths


def _over(summary: Sequence[Dict], config) -> str:
  if results_lib.over_training_seeds(summary):
    return f"{len(rundir.train_seeds(config))} training seeds, each on {config.eval.num_seeds} x " \
           f"{config.eval.rollouts_per_seed} rollouts"
  return f"{config.eval.num_seeds} seeds of {config.eval.rollouts_per_seed} rollouts"


def notes(summary: Sequence[Dict], num_seeds: int, rollouts_per_seed: int) -> str:
  """The lines under a table: what a cell is, and rollouts lost to worker crashes."""
  if results_lib.over_training_seeds(summary):
    trained = max(len(r["per_seed"]) for r in summary)
    lines = [f"Mean ± std (ddof=0) over {trained} training seed(s) of the policy, each evaluated on {num_seeds} "
             f"evaluation seed(s) x {rollouts_per_seed} rollouts; \"none\" = the training distribution."]
  else:
    lines = [f"Mean ± std (ddof=0) over {num_seeds} evaluation seed(s) of {rollouts_per_seed} rollouts each; "
             "\"none\" = the training distribution."]
  for r in summary:
    if r["crashed"]:
      lines.append(f"- {r['task']}/{tables.encoder_name(r['encoder'])}/{tables.level_name(r['level'])}: "
                   f"{r['crashed']} rollout(s) lost to simulator worker crashes, left out.")
  return "\n".join(lines)


def run(config, workdir: str) -> None:
  """The evaluate stage (see the module docstring): the trained policy of `workdir` in the sim bridge's pool."""
  # pylint: disable=import-outside-toplevel
  from roboshape.sim import EnvSpec, SimPool, SimWorkerError
  from roboshape.train import bc
  rollout_plan(tuple(config.eval.levels), config.eval.num_seeds, config.eval.rollouts_per_seed,
               config.eval.seed_offset)     # bad settings fail before the policy loads
  make_pool = lambda level: SimPool(EnvSpec.from_config(config, level=level), num_workers=config.sim.num_workers)
  slot_video = _slot_video_fn(config, workdir)
  for i, train_seed in enumerate(rundir.train_seeds(config)):
    policy = bc.acting_policy(workdir, train_seed=train_seed)    # a policy that cannot act is blamed in one line
    fingerprint = policy_fingerprint(workdir, train_seed, config.policy.eval.to_dict())
    evaluate(config, workdir, policy, make_pool, SimWorkerError, fingerprint, train_seed=train_seed,
             videos_per_level=config.eval.videos_per_level if i == 0 else 0, slot_video=slot_video)


def evaluate(config, workdir: str, policy, make_pool: Callable[[str], object], worker_error=Exception,
             fingerprint: str = "", train_seed=None, videos_per_level: Optional[int] = None,
             slot_video: Optional[Callable[[np.ndarray], np.ndarray]] = None) -> Dict[str, str]:
  """Runs the rollouts not yet in the policy's log (`rundir.rollout_log`), then writes all outputs; returns their paths.

  `make_pool(level)` returns a context manager giving a pool (see `run_rollouts`); `fingerprint` identifies the
  policy, so a log of another policy is set aside rather than resumed. With policy.train_seeds, `train_seed` names
  the policy's seed: its rollouts carry it, and the outputs cover every training seed's log so far.
  `videos_per_level`: rollouts recorded per level (default config.eval.videos_per_level); `slot_video`: frames ->
  the frames of a second video of each recorded rollout (e.g. `videos.SaviSlotVideo`), none without it.
  """
  plan = rollout_plan(tuple(config.eval.levels), config.eval.num_seeds, config.eval.rollouts_per_seed,
                      config.eval.seed_offset)
  log = results_lib.ResultLog(rundir.rollout_log(workdir, train_seed), fingerprint)
  if videos_per_level is None:
    videos_per_level = config.eval.videos_per_level
  recorder = Recorder(config, log, rundir.videos_dir(workdir), slot_video, train_seed)
  # the set-aside policy's videos go with its log (only the policy that records videos has any there)
  recorder.clear_videos(set_aside=bool(log.set_aside and videos_per_level))
  start = time.time()
  for work in schedule(plan, log, videos_per_level, recorder.has_video):
    _run_level(config, work, policy, make_pool, worker_error, recorder)
  paths = write_outputs(config, workdir, merged_records(config, workdir, plan, log, train_seed))
  print(f"[roboshape] evaluation done in {time.time() - start:.0f}s: {os.path.abspath(paths['md'])}", flush=True)
  with open(paths["md"]) as f:
    print(f.read(), flush=True)
  return paths


@dataclasses.dataclass(frozen=True)
class LevelWork:
  """What one level of an evaluation still needs: `todo`, the planned rollouts not yet logged (those in `record`
  keep their frames for videos), and `missing`, logged rollouts of `record` whose video is missing (run again only
  to record it). `planned`, `done` and `successes` count the level's rollouts, and those logged so far (a rollout
  lost to a crashed worker is not counted), for the progress bar."""
  level: str
  todo: List[Rollout]
  record: List[Rollout]
  missing: List[Rollout]
  planned: int
  done: int
  successes: int


def schedule(plan: Sequence[Rollout], log: results_lib.ResultLog, videos_per_level: int,
             has_video: Callable[[Rollout, Dict], bool]) -> List[LevelWork]:
  """The work of each level of `plan`, in the plan's order, given what `log` holds: the first `videos_per_level`
  rollouts of a level are the recorded ones, and `has_video(rollout, its logged record)` says whether one that is
  logged has its video."""
  logged = {results_lib.key(rec): rec for rec in log.records}
  work = []
  for level in dict.fromkeys(r.level for r in plan):
    planned = [r for r in plan if r.level == level]
    counted = [rec for rec in log.records if rec["level"] == level and rec["ended"] != "worker_crash"]
    record = planned[:videos_per_level]
    work.append(LevelWork(
        level=level, todo=[r for r in planned if (r.level, r.seed) not in logged], record=record,
        missing=[r for r in record if (r.level, r.seed) in logged and not has_video(r, logged[(r.level, r.seed)])],
        planned=len(planned), done=len(counted), successes=sum(bool(rec["success"]) for rec in counted)))
  return work


def _run_level(config, work: LevelWork, policy, make_pool: Callable[[str], object], worker_error,
               recorder: "Recorder") -> None:
  """Runs the level's rollouts still to do, then re-records its missing videos, in one pool (none when neither)."""
  if not work.todo and not work.missing:
    print(f"[roboshape] evaluate {work.level}: all {work.planned} rollouts already done", flush=True)
    return
  label = f"{config.task}/{config.encoder}/{work.level}"
  with make_pool(work.level) as pool:
    if work.todo:
      run_rollouts(pool, policy, work.todo, recorder.on_done, record=work.record,
                   max_retries=config.eval.max_retries, worker_error=worker_error, desc=f"evaluate {label}",
                   initial=(work.done, work.successes))
    if work.missing:
      print(f"[roboshape] evaluate {work.level}: {len(work.missing)} video(s) missing from {recorder.video_dir}; "
            "re-recording their rollouts (the logged results stand)", flush=True)
      run_rollouts(pool, policy, work.missing, recorder.on_rerecorded, record=work.missing,
                   max_retries=config.eval.max_retries, worker_error=worker_error,
                   desc=f"re-record videos {label}")


class Recorder:
  """Where an evaluation's finished rollouts go: each one appended to the policy's log with the fields that
  identify it (task, encoder, training seed, level, seeds), and the frames of a recorded one written as its video
  <video_dir>/<level>_s<seed>_<ended>.{mp4,gif} (and, given a `slot_video` maker, as <...>_slots beside it)."""

  def __init__(self, config, log: results_lib.ResultLog, video_dir: str,
               slot_video: Optional[Callable[[np.ndarray], np.ndarray]] = None, train_seed=None):
    self.log, self.video_dir, self.slot_video = log, video_dir, slot_video
    self.fields = dict(task=config.task, encoder=columns.of_config(config),
                       **({} if train_seed is None else dict(train_seed=int(train_seed))))
    self.fps = config.eval.video_fps

  def clear_videos(self, set_aside: bool) -> None:
    """Deletes the temporary files of videos a killed run left half-written; with `set_aside` (the log of another
    policy was set aside), first moves the video folder to <video_dir>.stale, beside that log."""
    if set_aside and os.path.isdir(self.video_dir):
      shutil.rmtree(self.video_dir + ".stale", ignore_errors=True)
      os.replace(self.video_dir, self.video_dir + ".stale")
    videos.remove_partial(self.video_dir)

  def stem(self, r: Rollout, ended: str) -> str:
    return os.path.join(self.video_dir, f"{r.level}_s{r.seed}_{ended}")

  def has_video(self, r: Rollout, logged: Dict) -> bool:
    """Whether the logged rollout `r` has its video (a rollout lost to a crashed worker has none to make)."""
    return logged["ended"] == "worker_crash" or videos.exists(self.stem(r, logged["ended"]))

  def on_done(self, r: Rollout, result: Dict, frames: Optional[np.ndarray]) -> None:
    """`run_rollouts`' on_done: logs the rollout, and writes its videos when it was recorded."""
    self.log.append(dict(self.fields, level=r.level, seed_index=r.seed_index, rollout=r.rollout, seed=r.seed,
                         **result))
    if frames is not None:
      self._write_videos(r, result["ended"], frames)

  def on_rerecorded(self, r: Rollout, result: Dict, frames: Optional[np.ndarray]) -> None:
    """`run_rollouts`' on_done for a rollout run again for its missing video: writes the video and leaves the log
    as it is, saying so when the re-run ended otherwise than the logged one."""
    logged = next(rec for rec in self.log.records if results_lib.key(rec) == (r.level, r.seed))
    if frames is None:
      tqdm.write(f"[roboshape] the video of {r.level}/seed {r.seed} is still missing: its rollout lost its worker")
      return
    if (result["success"], result["length"]) != (logged["success"], logged["length"]):
      tqdm.write(f"[roboshape] note: re-recorded {r.level}/seed {r.seed} ended {result['ended']} after "
                 f"{result['length']} steps, the logged rollout {logged['ended']} after {logged['length']}")
    self._write_videos(r, result["ended"], frames)

  def _write_videos(self, r: Rollout, ended: str, frames: np.ndarray) -> None:
    path = self.stem(r, ended)
    videos.write_video(frames, path, fps=self.fps)
    if self.slot_video is not None:
      try:
        videos.write_video(self.slot_video(frames), path + "_slots", fps=self.fps, scale=2)
      except UserError as e:   # e.g. no SAVi checkpoint: the rollout itself stands
        tqdm.write(f"[roboshape] slot video of {path} left out: {e}")


def merged_records(config, workdir: str, plan: Sequence[Rollout], log: results_lib.ResultLog,
                   train_seed=None) -> List[Dict]:
  """The planned rollouts of every training seed's log so far, seed by seed: `log`, the one being written, for
  `train_seed`, the others as their files hold them."""
  keys = {(r.level, r.seed) for r in plan}
  records = []
  for seed in rundir.train_seeds(config):
    logged = log.records if seed == train_seed else results_lib.read_log(rundir.rollout_log(workdir, seed))
    records += [r for r in logged if results_lib.key(r) in keys]
  return records
