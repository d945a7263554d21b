"""Which runs of a workdir are done, running or pending, how far an unfinished stage got, and how long each stage
took.

  python -m roboshape.status WORKDIR          # a grid's workdir (configs/reproduce.py) or one run's

Reads the workdir's config.json and each run's stage log (<run>/stages.json, written by roboshape/stages.py). A run
is "done" when every stage it runs is done, "running" while a live process runs one of its stages, "stopped" when
the process that ran a stage is gone before it finished, or the run ended between two stages (run the same command
to resume), "skipped" when the grid skipped it (SKIPPED.json: a baseline without weights), and "pending" before any
stage but the collection started (a grid collects each task's dataset itself, in the stage log of the task's first
run, before any lane starts: that run waits for a lane like the others). A running or stopped
training stage says which seed it is at and that seed's newest saved step ("running (seed 2/3 at 1500/5000)"), an
evaluation how many rollouts its logs hold.

A grid's table ends with the wall time the grid itself has run so far (`grid_time`: its stage log's one entry,
summed over its restarts) and a rough estimate of the core-hours its unfinished runs have left (`estimate_left`): each
unfinished training or evaluation stage's remaining work (training steps over its seeds, rollouts) at a rate in
core-seconds per unit: a training stage's own pace between its two newest checkpoints of this attempt (`pace`), else
what the finished stages of its column (else of its encoder, for a column with options) took, else the unfinished
ones' pace or logged time over their saved work (the latter an overestimate by the work lost to kills and by the
compilations), else what the cells published where the grid publishes took (grid.publish: results it ran earlier,
perhaps on another machine; `published_rows`); an evaluation of a column none of whose rollouts are done takes every
column's rate (the simulator and renderer dominate it). It does not count collections and caches (minutes a run; a
task's collection is shared), nor that rollouts of a longer horizon cost more than the ones it was measured on.
"""
import os
import sys
from typing import Dict, List, Optional, Tuple

from roboshape import errors
from roboshape import grid
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.report import results as results_lib
from roboshape.errors import UserError


def _alive(pid) -> bool:
  try:
    os.kill(int(pid), 0)
  except (OSError, TypeError, ValueError):
    return False
  return True


ESTIMATED = ("pretrain", "train_policy", "evaluate")   # the stages `estimate_left` counts


def _training(config, run_dir: str, stage: str) -> Optional[Tuple[str, str]]:
  """(its folder, its config section) of a training stage that trains in this run: pretrain (unless it reuses
  another run's encoder) or train_policy; None for the other stages."""
  if stage == "pretrain" and not config.pretrain.get("from_workdir"):
    return rundir.pretrain_dir(run_dir, config.encoder), "pretrain"
  if stage == "train_policy":
    return rundir.policy_dir(run_dir), "policy"
  return None


def _seed_steps(config, stage_dir: str, stage: str) -> Tuple[List[int], int]:
  """([newest saved step of each seed of a training stage, 0 without a checkpoint], the stage's steps)."""
  steps = int(config[stage].train.steps)
  saved = [rundir.saved_steps(rundir.seed_dir(stage_dir, seed)) for seed in rundir.train_seeds(config, stage)]
  return [min(s[-1], steps) if s else 0 for s in saved], steps


def _training_progress(config, stage_dir: str, stage: str) -> str:
  """How far the seeds of a training stage are, from their newest saved checkpoints: "seed 2/3 at 1500/5000"
  (the first seed not yet at its last step), or "all 3 seeds trained"."""
  at, steps = _seed_steps(config, stage_dir, stage)
  for i, step in enumerate(at):
    if step < steps:
      return f"seed {i + 1}/{len(at)} at {step}/{steps}"
  return f"all {len(at)} seeds trained"


def planned(config, stage: str) -> Optional[int]:
  """A stage's work in all, from the config alone: training steps summed over its seeds (pretrain, train_policy; a
  pretrain that reuses another run's encoder has none) or rollouts (evaluate); None for the other stages."""
  if stage == "pretrain":
    return 0 if config.pretrain.get("from_workdir") else (
        int(config.pretrain.train.steps) * len(rundir.train_seeds(config, "pretrain")))
  if stage == "train_policy":
    return int(config.policy.train.steps) * len(rundir.train_seeds(config))
  if stage == "evaluate":
    return (len(rundir.train_seeds(config)) * len(config.eval.levels) * int(config.eval.num_seeds)
            * int(config.eval.rollouts_per_seed))
  return None


def work(config, run_dir: str, stage: str) -> Optional[Tuple[int, int]]:
  """(done, in all) of a stage's work (`planned`), the done part from what it saved: its seeds' newest
  checkpoints or the rollouts in its logs; None for the stages `planned` does not count."""
  total = planned(config, stage)
  if not total:
    return None if total is None else (0, 0)
  if stage == "evaluate":
    return sum(len(results_lib.read_log(rundir.rollout_log(run_dir, s))) for s in rundir.train_seeds(config)), total
  at, _ = _seed_steps(config, *_training(config, run_dir, stage))
  return sum(at), total


def pace(config, run_dir: str, stage: str, since: float, cores: int = 1) -> Optional[Tuple[float, int]]:
  """(core-seconds, steps) between the two newest checkpoints of the seed a training stage (pretrain, train_policy)
  saved last, when both were written after `since` (the epoch time its current attempt began, so no stop lies between
  them): the pace the stage trains at now, without the compilations and the work lost to kills that its logged
  time holds. None when there are no such two checkpoints."""
  training = _training(config, run_dir, stage)
  if training is None:
    return None
  stage_dir, section = training
  newest = None
  for seed in rundir.train_seeds(config, section):
    seed_dir = rundir.seed_dir(stage_dir, seed)
    try:                  # (a running stage may delete its oldest checkpoint between the listing and the reading)
      saved = [(os.path.getmtime(os.path.join(rundir.checkpoints(seed_dir), str(step))), step)
               for step in rundir.saved_steps(seed_dir)[-2:]]
    except OSError:
      continue
    if len(saved) == 2 and (newest is None or saved[1][0] > newest[1][0]):
      newest = saved
  if newest is None:
    return None
  (t0, s0), (t1, s1) = newest
  if t0 < since or t1 <= t0 or s1 <= s0:
    return None
  return (t1 - t0) * cores, s1 - s0


def progress(config, run_dir: str, stage: str) -> str:
  """How far an unfinished stage of a run got, from what it saved: its training seeds' checkpoints (pretrain,
  train_policy) or the rollouts in its logs (evaluate); "" for the other stages."""
  training = _training(config, run_dir, stage)
  if training is not None:
    return _training_progress(config, *training)
  if stage == "evaluate":
    done, total = work(config, run_dir, stage)
    return f"{done}/{total} rollouts"
  return ""


def _entry_state(entry: dict) -> str:
  """"done", "running" (its process alive), "stopped" (its process gone before it finished) or "pending" (never
  started) of one entry of a stage log."""
  if entry.get("state") == "done":
    return "done"
  if entry.get("state") == "running":
    return "running" if _alive(entry.get("pid")) else "stopped"
  return "pending"


def run_status(stages, run_dir: str, config=None) -> Dict:
  """{state, stages: {stage: seconds or state}, seconds, core_hours} of one run whose config runs `stages`; the
  totals count a stage still running (or killed) up to its last beat (rundir.logged_time). With the run's
  `config`, an unfinished stage's state says how far it got (`progress`)."""
  if os.path.exists(os.path.join(run_dir, rundir.SKIPPED_FILE)):
    return dict(state="skipped", stages={}, seconds=0.0, core_hours=0.0)
  log = rundir.read_stage_log(run_dir, strict=True)
  per_stage, states = {}, []
  for stage in stages:
    entry = log.get(stage, {})
    state = _entry_state(entry)
    states.append(state)
    done_so_far = progress(config, run_dir, stage) if config is not None and state != "pending" else ""
    per_stage[stage] = entry.get("seconds") if state == "done" else (
        f"{state} ({done_so_far})" if done_so_far else state)
  if all(s == "done" for s in states):
    state = "done"
  elif "running" in states:
    state = "running"
  elif "stopped" in states or any(s == "done" and stage != "collect" for stage, s in zip(stages, states)):
    state = "stopped"
  else:
    state = "pending"
  times = [rundir.logged_time(entry) for entry in log.values() if isinstance(entry, dict)]
  return dict(state=state, stages=per_stage, seconds=sum(t[0] for t in times),
              core_hours=sum(t[1] for t in times) / 3600,
              stage_core_seconds={stage: rundir.logged_time(entry)[1] for stage, entry in log.items()
                                  if isinstance(entry, dict)},
              attempts={stage: (float(entry["attempt"]), int(entry.get("cores", 1))) for stage, entry in log.items()
                        if isinstance(entry, dict) and entry.get("state") == "running" and "attempt" in entry})


def estimate_left(rows: List[Dict], published: List[Dict] = ()) -> None:
  """Sets each unfinished run's row's `left`: the rough core-hours its stages of ESTIMATED have left (module
  docstring), None where neither its own pace nor any stage of its column or encoder gives a rate; None too for a
  done or skipped run; and `published_rate` True where a published cell's rate (`published`: `published_rows`, the
  last resort) went into it. Rows need `config` and `run_dir` (`workdir_status` gives them)."""
  def keys(column, stage):   # its column's rate, else its encoder's (a column with options), else any column's rollouts
    return tuple(dict.fromkeys(((column, stage), (columns.parse(column)[0], stage))
                               + ((("*", stage),) if stage == "evaluate" else ())))

  def measured(i, r, stage):
    """(core-seconds, units, how) a stage of a row measured, or None: a finished stage's whole work ("finished"),
    else an unfinished one's `pace` ("pace"), else its logged time over the work it saved ("saved")."""
    state = r["stages"].get(stage, "pending")
    if isinstance(state, (int, float)):
      units = planned(r["config"], stage)
      return (r["stage_core_seconds"].get(stage, 0.0), units, "finished") if units else None
    if state == "pending":
      return None
    now = pace(r["config"], r["run_dir"], stage, *r["attempts"][stage]) if stage in r.get("attempts", {}) else None
    if now:
      return now + ("pace",)
    done = (saved[i, stage] or (0, 0))[0]
    return (r["stage_core_seconds"].get(stage, 0.0), done, "saved") if done else None

  saved = {(i, stage): work(r["config"], r["run_dir"], stage)     # each unfinished stage's (done, in all), read once
           for i, r in enumerate(rows) for stage in ESTIMATED
           if stage in r["stages"] and not isinstance(r["stages"][stage], (int, float))}
  found = {(i, stage): measured(i, r, stage) for i, r in enumerate(rows) for stage in ESTIMATED}
  rated = [(rows[i]["encoder"], stage, m, 0 if m[2] == "finished" else 1) for (i, stage), m in found.items() if m]
  for r in published:                                             # their finished stages alone
    for stage in ESTIMATED:
      m = measured(None, r, stage) if isinstance(r["stages"].get(stage), (int, float)) else None
      if m:
        rated.append((r["encoder"], stage, m, 2))
  spent, units = {}, {}    # per (key, tier): this workdir's finished stages (0), its unfinished ones (1), published (2)
  for encoder, stage, m, tier in rated:
    for key in keys(encoder, stage):
      key = key + (tier,)
      spent[key], units[key] = spent.get(key, 0.0) + m[0], units.get(key, 0) + m[1]
  for i, r in enumerate(rows):
    r["left"], r["published_rate"] = None, False
    if r["state"] in ("done", "skipped"):
      continue
    left = 0.0
    for stage in ESTIMATED:
      if stage not in r["stages"] or isinstance(r["stages"][stage], (int, float)):
        continue
      done, total = saved[i, stage]
      if total <= done:
        continue
      own = found[i, stage]
      if own and own[2] == "pace":
        rate = own[0] / own[1]                                          # its own pace, now
      else:
        key = next((k + (tier,) for tier in (0, 1, 2) for k in keys(r["encoder"], stage)
                    if units.get(k + (tier,))), None)
        if key is None:
          left = None
          break
        rate = spent[key] / units[key]
        r["published_rate"] |= key[-1] == 2
      left += (total - done) * rate / 3600
    r["left"] = left


def workdir_status(workdir: str, config=None) -> List[Dict]:
  """One row per run of the workdir: task, encoder (its column: roboshape/encoders/columns.py), run_dir and
  `run_status`'s fields. `config`: the workdir's config.json when the caller has read it already."""
  config = config if config is not None else rundir.load_config(workdir)
  if "grid" in config:
    runs = list(grid.grid_configs(config, workdir))
  else:
    runs = [(config.task, columns.of_config(config), config, workdir)]
  rows = [dict(task=t, encoder=e, run_dir=d, config=sub, **run_status(tuple(sub.stages), d, sub))
          for t, e, sub, d in runs]
  estimate_left(rows, published_rows(config))
  return rows


def published_rows(config) -> List[Dict]:
  """Rows (as `workdir_status` makes them) of the cells published where a grid publishes (grid.publish, relative to
  the current folder), each with its published config.json and stage log; `estimate_left`'s last resort for a
  column no run of the grid gives a rate yet. A cell whose files cannot be read is left out (the report is where a
  damaged cell is refused); [] for one run's workdir or a grid that does not publish."""
  root = config.grid.get("publish", "") if "grid" in config else ""
  if not root or not os.path.isdir(root):
    return []
  rows = []
  for name in sorted(os.listdir(root)):
    folder = os.path.join(root, name)
    if not os.path.isfile(rundir.config_path(folder)) or not os.path.isfile(rundir.stage_log_path(folder)):
      continue
    try:
      sub = rundir.load_config(folder)
      rows.append(dict(task=sub.task, encoder=columns.of_config(sub), run_dir=folder, config=sub,
                       **run_status(tuple(sub.stages), folder)))
    except UserError:
      continue
  return rows


def grid_time(workdir: str) -> Optional[str]:
  """A line on the wall time a grid's process has run (rundir.GRID_CLOCK in the grid workdir's stage log, summed
  over its attempts, an unfinished one up to its last beat): None before a grid that logs it first ran."""
  entry = rundir.read_stage_log(workdir, strict=True).get(rundir.GRID_CLOCK)
  if not isinstance(entry, dict):
    return None
  seconds, state = rundir.logged_time(entry)[0], _entry_state(entry)
  now = {"done": f"finished {entry.get('finished', '?')}", "running": "running now"}.get(state, state)
  return (f"The grid has run {_duration(seconds)} of wall time since {entry.get('started', '?')}, over its "
          f"restarts ({now}).")


def _duration(seconds) -> str:
  if not isinstance(seconds, (int, float)):
    return str(seconds)
  minutes, s = divmod(int(round(seconds)), 60)
  return f"{minutes // 60}h{minutes % 60:02d}m" if minutes >= 60 else f"{minutes}m{s:02d}s"


def _left(value) -> str:
  return "" if value is None else f"~{value:.1f}"


def render(rows: List[Dict], lanes: int = 1) -> str:
  """A markdown table: one line per run, its state, each stage's wall time (or state), the total wall time, the
  core-hours (rundir.read_stage_log: each attempt's wall time times the cores it held) and, with `left` in the
  rows (`estimate_left`), the core-hours each has left and their sum; with `lanes` (a grid's runs at a time, one core
  each) above one, also that sum over the lanes: the wall time left if they stay busy to the end."""
  stages = [s for s in rundir.STAGES if any(s in r["stages"] for r in rows)]
  estimated = any("left" in r for r in rows)
  extra = " left (est.) |" if estimated else ""
  lines = ["| task | encoder | state | " + " | ".join(stages) + " | total | core-hours |" + extra,
           "| --- | --- | --- | " + " | ".join("---" for _ in stages) + " | --- | --- |"
           + (" --- |" if estimated else "")]
  for r in rows:
    cells = [_duration(r["stages"][s]) if s in r["stages"] else "" for s in stages]
    lines.append(f"| {r['task']} | {r['encoder']} | {r['state']} | " + " | ".join(cells)
                 + f" | {_duration(r['seconds'])} | {r['core_hours']:.2f} |"
                 + (f" {_left(r.get('left'))} |" if estimated else ""))
  counts = {}
  for r in rows:
    counts[r["state"]] = counts.get(r["state"], 0) + 1
  lines += ["", ", ".join(f"{n} {state}" for state, n in sorted(counts.items())) + f" of {len(rows)} run(s)"]
  if estimated:
    unknown = [f"{r['task']} x {r['encoder']}" for r in rows
               if r.get("left") is None and r["state"] not in ("done", "skipped")]
    if unknown and not any(r.get("left") is not None for r in rows):
      lines.append("No estimate of the core-hours left yet: no stage of these runs' columns or encoders has finished "
                   "or saved work to take a rate from.")
    else:
      left = sum(r['left'] or 0.0 for r in rows)
      borrowed = [f"{r['task']} x {r['encoder']}" for r in rows
                  if r.get("left") is not None and r.get("published_rate")]
      lines.append(f"About {left:.1f} core-hours left, at the training stages' own "
                   "pace and the rates of the finished stages (collections and caches not counted)"
                   + (f"; {', '.join(borrowed)} partly at the rates of the cells published where the grid publishes "
                      "(grid.publish), perhaps on another machine" if borrowed else "")
                   + (f"; no rate yet for {', '.join(unknown)}" if unknown else "")
                   + (f"; at least {left / lanes:.1f} hours of wall time on the grid's {lanes} lanes (grid.lanes, "
                      "one core each)" if lanes > 1 else "") + ".")
  return "\n".join(lines)


def main(argv) -> int:
  if len(argv) != 2 or argv[1].startswith("-"):
    print("usage: python -m roboshape.status WORKDIR", file=sys.stderr)
    return 2
  try:
    config = rundir.load_config(argv[1])
    print(render(workdir_status(argv[1], config),
                 lanes=int(config.grid.get("lanes", 1)) if "grid" in config else 1))
    clock = grid_time(argv[1]) if "grid" in config else None
    if clock:
      print(clock)
  except UserError as e:
    return errors.print_error(e)
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv))
