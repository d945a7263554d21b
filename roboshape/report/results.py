"""Rollout records: an append-only JSON-lines log that survives crashes, and the statistics the tables print.

Every finished rollout is one line of <workdir>/eval/results.jsonl, flushed at once, so a killed evaluation keeps
what it finished and a rerun skips it. A record:

  {"task": "push", "encoder": "savi", "level": "L1", "seed_index": 0, "rollout": 7, "seed": 1000000007,
   "success": true, "length": 83, "ended": "success", "reached": ["moved", "halfway", "on_target"],
   "policy": "<fingerprint>"}

`ended` is "success" (the env's success check fired), "horizon" (the episode ran to its step limit) or
"worker_crash" (the simulator worker died on this rollout more often than allowed: the rollout is reported and
left out of the statistics). `reached` names the task's milestones (roboshape.envs.MILESTONES) the rollout reached
at some step; logs written before milestones were recorded have none, nor do they have `closest_cube_cm` and
`first_move` (where a failure is lost: roboshape/eval/closed_loop.py). Success rates are computed per evaluation
seed (over its rollouts), then mean +- std (population std, ddof=0) over seeds, as in the paper's tables.
"""
import csv
import io
import json
import os
from typing import Dict, Iterable, List, Sequence

import numpy as np

from roboshape import fileio

CSV_FIELDS = ("task", "encoder", "train_seed", "level", "seed_index", "rollout", "seed", "success", "length", "ended",
              "reached", "closest_cube_cm", "first_move")


def key(record: Dict) -> tuple:
  """What identifies a rollout in a log: its level and env seed."""
  return (record["level"], int(record["seed"]))


class ResultLog:
  """The JSON-lines log of one evaluation; records from another policy (`fingerprint`) are set aside."""

  def __init__(self, path: str, fingerprint: str = ""):
    self.path = path
    self.fingerprint = fingerprint
    self.records: List[Dict] = []
    self.set_aside = False                   # True when the log held another policy's results
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    if os.path.exists(path):
      self.records = _read_jsonl(path)
      if any(r.get("policy", "") != fingerprint for r in self.records):
        os.replace(path, path + ".stale")    # another policy's results: keep them aside, start afresh
        self.records, self.set_aside = [], True
    self._done = {key(r) for r in self.records}

  def done(self, level: str, seed: int) -> bool:
    return (level, int(seed)) in self._done

  def append(self, record: Dict) -> None:
    record = dict(record, policy=self.fingerprint)
    with open(self.path, "a") as f:
      f.write(json.dumps(record) + "\n")
      f.flush()
      os.fsync(f.fileno())
    self.records.append(record)
    self._done.add(key(record))


def read_log(path: str) -> List[Dict]:
  """The records of a log as they are (none when it is missing), without checking whose policy made them."""
  return _read_jsonl(path) if os.path.exists(path) else []


def _read_jsonl(path: str) -> List[Dict]:
  records = []
  with open(path) as f:
    for line in f:
      line = line.strip()
      if not line:
        continue
      try:
        records.append(json.loads(line))
      except json.JSONDecodeError:
        break           # a line cut by a crash mid-write: everything before it is whole
  return records


OVER_TRAINING_SEEDS = "training seeds"     # a summary row's `over` when its std is over training seeds


def over_training_seeds(summary: Iterable[Dict]) -> bool:
  """Whether summary rows give mean ± std over training seeds (policy.train_seeds) rather than evaluation seeds."""
  return any(r.get("over") == OVER_TRAINING_SEEDS for r in summary)


def summarize(records: Iterable[Dict]) -> List[Dict]:
  """One row per (task, encoder, level): the mean and std of the success rate over seeds.

  Over training seeds when the records come from policies of more than one (`train_seed`, policy.train_seeds):
  each policy's rate pools its evaluation seeds' rollouts. Otherwise over evaluation seeds (`seed_index`).
  Returns rows {task, encoder, level, mean, std, over: "training seeds" | "evaluation seeds", per_seed: [rate, ...],
  rollouts, successes, crashed, mean_length}, ordered by task, encoder and level as first seen.
  """
  records = list(records)
  by_training = len({r.get("train_seed") for r in records}) > 1
  field = "train_seed" if by_training else "seed_index"
  groups: Dict[tuple, Dict[int, List[Dict]]] = {}
  for r in records:
    groups.setdefault((r["task"], r["encoder"], r["level"]), {}).setdefault(int(r[field]), []).append(r)
  rows = []
  for (task, encoder, level), seeds in groups.items():
    counted = {s: [r for r in rs if r["ended"] != "worker_crash"] for s, rs in sorted(seeds.items())}
    per_seed = [float(np.mean([bool(r["success"]) for r in rs])) for rs in counted.values() if rs]
    finished = [r for rs in counted.values() for r in rs]
    rows.append(dict(
        task=task, encoder=encoder, level=level,
        mean=float(np.mean(per_seed)) if per_seed else None,
        std=float(np.std(per_seed)) if per_seed else None,
        over=OVER_TRAINING_SEEDS if by_training else "evaluation seeds",
        per_seed=per_seed,
        rollouts=len(finished),
        successes=int(sum(bool(r["success"]) for r in finished)),
        crashed=sum(len(rs) for rs in seeds.values()) - len(finished),
        mean_length=float(np.mean([r["length"] for r in finished])) if finished else None))
  return rows


def write_csv(path: str, records: Sequence[Dict]) -> None:
  text = io.StringIO(newline="")
  writer = csv.DictWriter(text, fieldnames=CSV_FIELDS, extrasaction="ignore")
  writer.writeheader()
  for r in records:
    writer.writerow(dict(r, reached="+".join(r.get("reached", ()))))
  fileio.atomic_write_text(path, text.getvalue())


def milestone_counts(records: Iterable[Dict], names: Sequence[str]) -> List[Dict]:
  """Per level (as first seen), over the rollouts that recorded milestones: {level, rollouts, failures, reached:
  {name: rollouts that reached it}, failed_reached: {name: failed rollouts that reached it}}."""
  rows: Dict[str, Dict] = {}
  for r in records:
    if r["ended"] == "worker_crash" or "reached" not in r:
      continue
    row = rows.setdefault(r["level"], dict(level=r["level"], rollouts=0, failures=0,
                                           reached={n: 0 for n in names}, failed_reached={n: 0 for n in names}))
    row["rollouts"] += 1
    row["failures"] += int(not r["success"])
    for name in names:
      if name in r["reached"]:
        row["reached"][name] += 1
        row["failed_reached"][name] += int(not r["success"])
  return list(rows.values())
