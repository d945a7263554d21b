"""A study of probes: one row per run, read from the run's own files, in a CSV and a README table built from it.

A probe is an ordinary run (launch.py) that differs from its experiment config in a few fields. `add` reads its
workdir and writes one row to <study>/probes.csv (replacing a row of the same name):

  probe, task, encoder, variant   the run's identity
  changed                         every config field that differs from `configs/common.get_config(task, encoder,
                                  scale)`, scale the variant up to any "_" (an old run's may carry a suffix, e.g.
                                  small_chunk), or for a field removed from the configs from the default it had
                                  (rundir.REMOVED), except the bookkeeping ones (IGNORED: the dataset path, the
                                  run whose pretrained encoder it serves, worker count, the evaluated levels,
                                  stages, seeds of the run itself). A study whose
                                  probes started from other defaults than today's (a recipe adopted since) states
                                  those in <study>/baseline.json ({"task or *": {"dotted.field": value}}), and its
                                  rows name what changed from them
  rollouts, successes, success    the evaluation's rollouts at the train level (every training seed pooled)
  reached                         per milestone of the task, how many of those rollouts reached it
  val_mse_best, best_step, val_mse_last   the policy's validation action MSE (roboshape/train/bc.py), seed 0
  fg_ari                          the selected SAVi's final validation FG-ARI, where the run pretrained one
  cube_iou, cube_found            the same SAVi's best slot IoU with the cube and the share of frames in which a
                                  slot found it (roboshape/eval/slots.py), where its log has them
  closest_cm, first_move          medians over those rollouts of the tool centre point's closest distance to the
                                  cube and of the first actions' length (roboshape/eval/closed_loop.py); empty for
                                  a log that predates them
  first_move_offline, first_move_expert, mse_approach, mse_grasp, mse_lift, mse_first
                                  the offline figures of roboshape/eval/offline.py (eval/offline.json, where the
                                  probe's workdir has one): first moves predicted on the validation demos and the
                                  expert's, and the action MSE per phase
  <stage>_s, cores, core_hours    each stage's wall seconds (stages.json; collect excluded: the dataset is shared
                                  by a task's probes), the most cores a stage held, and the stages' core-seconds
                                  (rundir.logged_time: wall time x the cores held; one core where the log predates
                                  that record) in hours

`add` also copies those files (KEPT) to <study>/<probe>/, so the row can be read again from the repository.
`render` writes the table between the README's markers (BEGIN, END) from the CSV alone, so the README cannot
quote a number the CSV does not hold (tests/test_study.py checks the committed study).

  python -m roboshape.study STUDY_DIR WORKDIR --name NAME   # add a probe, rebuild the README
  python -m roboshape.study STUDY_DIR                       # rebuild the README from the CSV
"""
import argparse
import csv
import io
import json
import os
import sys
from typing import Dict, List, Optional

import numpy as np

from roboshape import errors
from roboshape import fileio
from roboshape import rundir
from roboshape.envs import MILESTONES
from roboshape.errors import UserError

CSV_NAME = "probes.csv"
README_NAME = "README.md"
BASELINE_NAME = "baseline.json"
BEGIN, END = "<!-- probes:begin (generated from probes.csv by roboshape.study) -->", "<!-- probes:end -->"
IGNORED = ("data.dir", "pretrain.from_workdir", "sim.num_workers", "eval.levels", "stages", "policy.train_seeds",
           "pretrain.train_seeds", "seed", "name", "variant")
# What a probe keeps in the study (<study>/<probe>/, same layout): everything its row is read from, and the
# evaluation's milestone table and the policy's validation curve.
KEPT = ("config.json", "stages.json", "eval/results.csv", "eval/milestones.md", "policy/val_metrics.json",
        "policy/val_metrics.png", "policy/seed_0/val_metrics.json", "savi/selected.json", "savi/val_metrics.json",
        "savi/val_metrics.png", "eval/offline.json")
TIMED = ("pretrain", "cache", "train_policy", "evaluate")
# Where success is lost (closed loop, then offline): a second table, of the rows that hold them.
DIAGNOSED = ("closest_cm", "first_move", "first_move_offline", "first_move_expert", "mse_approach", "mse_grasp",
             "mse_lift", "mse_first")
COLUMNS = (("probe", "task", "encoder", "variant", "changed", "rollouts", "successes", "success", "reached",
            "val_mse_best", "best_step", "val_mse_last", "fg_ari") + tuple(f"{s}_s" for s in TIMED)
           + ("cores", "core_hours") + DIAGNOSED + ("cube_iou", "cube_found"))


def _flatten(tree, prefix: str = "") -> Dict:
  out = {}
  for key, value in tree.items():
    path = f"{prefix}{key}"
    if isinstance(value, dict):
      out.update(_flatten(value, path + "."))
    else:
      out[path] = tuple(value) if isinstance(value, list) else value
  return out


def _unread_sections(encoder: str) -> set:
  """The config sections only other encoders read (encoders.Kind.sections): a value there changes nothing in a run
  of `encoder` (e.g. the ae section of an old SAVi run, copied from its savi section by rundir.upgrade_config)."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  own = {s.split(".")[0] for s in encoders.get(encoder).sections}
  every = {s.split(".")[0] for name in encoders.names() for s in encoders.get(name).sections}
  return every - own


def changed_fields(config: Dict, baseline: Optional[Dict] = None) -> str:
  """"a=1; b.c=(2, 3)": the fields of a run's config.json that differ from its experiment's defaults (a field added
  to the configs after the run was made reads as the value the run had, rundir.ADDED, a change where today's
  default differs; one removed since is compared with the default it had, rundir.REMOVED), or from `baseline` where it names the field: a study's
  baseline.json, {"*" or a task: {"dotted.field": value}}, the task's entries over "*"'s."""
  from configs import common  # pylint: disable=import-outside-toplevel
  scale = config["variant"].partition("_")[0]
  baseline = baseline or {}
  default = {**{k: d for k, (d, _) in rundir.REMOVED.items()},
             **_flatten(common.get_config(config["task"], config["encoder"], scale).to_dict()),
             **{k: tuple(v) if isinstance(v, list) else v
                for k, v in {**baseline.get("*", {}), **baseline.get(config["task"], {})}.items()}}
  ran = _flatten(config)
  unread = _unread_sections(config["encoder"])
  keys = sorted(k for k in ran
                if ran[k] != default.get(k) and k.split(".")[0] not in unread
                and not any(k == i or k.startswith(i + ".") for i in IGNORED))
  return "; ".join(f"{k}={ran.get(k)!r}" for k in keys)


def _train_rollouts(workdir: str) -> List[Dict]:
  path = os.path.join(workdir, "eval", rundir.RESULTS_CSV)
  if not os.path.exists(path):
    raise UserError(f"{path} does not exist: evaluate the run first (its `evaluate` stage).")
  with open(path, newline="") as f:
    return [r for r in csv.DictReader(f) if r["level"] == "train"]


def _val_metrics(workdir: str) -> List[Dict]:
  for rel in ("policy/seed_0/val_metrics.json", "policy/val_metrics.json"):
    path = os.path.join(workdir, rel)
    if os.path.exists(path):
      with open(path) as f:
        return json.load(f)
  return []


def _fg_ari(workdir: str, key: str = "fg_ari") -> str:
  """The served SAVi's final validation FG-ARI (or another of its metrics, `key`): the selected seed's
  (savi/selected.json), else the single run's; "" where the run has no SAVi or its log lacks the metric."""
  for rel in (f"savi/{rundir.SELECTION_FILE}", "savi/val_metrics.json"):
    path = os.path.join(workdir, rel)
    if not os.path.exists(path):
      continue
    with open(path) as f:
      data = json.load(f)
    if isinstance(data, dict):
      data = [s for s in data.get("seeds", []) if s.get("seed") == data.get("selected_seed")]
    if data and key in data[-1]:
      return f"{data[-1][key]:.3f}"
  return ""


def _median(rollouts: List[Dict], field: str, digits: int) -> str:
  values = [float(r[field]) for r in rollouts if r.get(field) not in (None, "")]
  return f"{np.median(values):.{digits}f}" if values else ""


def _diagnosis(workdir: str, rollouts: List[Dict]) -> Dict:
  """The DIAGNOSED columns of a probe: closed-loop medians, and the offline figures where eval/offline.json is."""
  row = dict.fromkeys(DIAGNOSED, "")
  row.update(closest_cm=_median(rollouts, "closest_cube_cm", 1), first_move=_median(rollouts, "first_move", 2))
  path = os.path.join(workdir, "eval", "offline.json")
  if os.path.exists(path):
    with open(path) as f:
      offline = json.load(f)
    row.update(first_move_offline=f"{offline['first_move']['policy']:.2f}",
               first_move_expert=f"{offline['first_move']['expert']:.2f}")
    for phase, figures in offline["phases"].items():
      row[f"mse_{phase}"] = "" if figures["action_mse"] is None else f"{figures['action_mse']:.4f}"
  return row


def read_baseline(study: str) -> Dict:
  """<study>/baseline.json (see the module docstring), or {} where the study has none."""
  path = os.path.join(study, BASELINE_NAME)
  if not os.path.exists(path):
    return {}
  with open(path) as f:
    return json.load(f)


def probe_row(workdir: str, name: str, baseline: Optional[Dict] = None) -> Dict:
  """The study's row of the evaluated run in `workdir` (see the module docstring); `baseline`: the study's
  read_baseline."""
  config = rundir.load_config(workdir).to_dict()
  rollouts = _train_rollouts(workdir)
  if not rollouts:
    raise UserError(f"{workdir} has no train-level rollouts in eval/results.csv: evaluate the train level.")
  wins = sum(r["success"] == "True" for r in rollouts)
  reached = [m for r in rollouts for m in r["reached"].split("+") if m]
  metrics = [m for m in _val_metrics(workdir) if "action_mse" in m]
  best = min(metrics, key=lambda m: m["action_mse"]) if metrics else None
  stages = rundir.read_stage_log(workdir)
  timed = {s: stages[s] for s in TIMED if s in stages}
  seconds = {s: rundir.logged_time(timed[s])[0] if s in timed else None for s in TIMED}
  core_seconds = sum(rundir.logged_time(entry)[1] for entry in timed.values())
  cores = max((int(entry.get("cores", 1)) for entry in timed.values()), default=1)
  row = dict(probe=name, task=config["task"], encoder=config["encoder"], variant=config["variant"],
             changed=changed_fields(config, baseline) or "(none)", rollouts=len(rollouts), successes=wins,
             success=f"{wins / len(rollouts):.2f}",
             reached=" ".join(f"{m} {reached.count(m)}" for m in MILESTONES[config["task"]]),
             val_mse_best=f"{best['action_mse']:.4f}" if best else "", best_step=best["step"] if best else "",
             val_mse_last=f"{metrics[-1]['action_mse']:.4f}" if metrics else "", fg_ari=_fg_ari(workdir),
             cores=cores, core_hours=f"{core_seconds / 3600:.2f}")
  row.update({f"{s}_s": "" if v is None else f"{v:.0f}" for s, v in seconds.items()})
  row.update(_diagnosis(workdir, rollouts))
  row.update(cube_iou=_fg_ari(workdir, "cube_iou"), cube_found=_fg_ari(workdir, "cube_found"))
  return row


def read_rows(study: str) -> List[Dict]:
  path = os.path.join(study, CSV_NAME)
  if not os.path.exists(path):
    return []
  with open(path, newline="") as f:
    return list(csv.DictReader(f))


def write_rows(study: str, rows: List[Dict]) -> None:
  out = io.StringIO()
  writer = csv.DictWriter(out, fieldnames=COLUMNS, lineterminator="\n")
  writer.writeheader()
  writer.writerows(rows)
  fileio.atomic_write_text(os.path.join(study, CSV_NAME), out.getvalue())


def table(rows: List[Dict]) -> str:
  """The README's markdown table of `rows` (the CSV's rows, as strings)."""
  head = ("| probe | task x encoder | changed from `:small` | train success | milestones reached | val action MSE "
          "best (step) / last | FG-ARI (cube IoU, found) | train_policy + evaluate (s) | core-h |")
  lines = [head, "|" + " --- |" * head.count(" | ") + " --- |"]
  for r in rows:
    lines.append(f"| {r['probe']} | {r['task']} x {r['encoder']} | {r['changed']} | "
                 f"{r['success']} ({r['successes']}/{r['rollouts']}) | {r['reached']} | "
                 f"{r['val_mse_best']} ({r['best_step']}) / {r['val_mse_last']} | {_savi_scores(r)} | "
                 f"{r['train_policy_s']} + {r['evaluate_s']} | {r['core_hours']} |")
  diagnosed = [r for r in rows if any(r.get(k) for k in DIAGNOSED)]
  if diagnosed:
    lines += ["", "Where success is lost, for the probes that measured it: the tool centre point's closest distance "
              "to the cube (median over the train-level rollouts); the length of the first actions' position part "
              "(median; controller units, each axis at most 1) in closed loop, predicted offline on the validation "
              "demos, and the expert's; the offline action MSE on the validation demos by phase "
              "(roboshape/eval/offline.py).", "",
              "| probe | train success | closest to cube (cm) | first moves: closed loop / offline / expert | "
              "offline MSE approach / grasp / lift / first steps |", "| --- | --- | --- | --- | --- |"]
    for r in diagnosed:
      v = {k: r.get(k) or "-" for k in DIAGNOSED}
      lines.append(f"| {r['probe']} | {r['success']} | {v['closest_cm']} | {v['first_move']} / "
                   f"{v['first_move_offline']} / {v['first_move_expert']} | {v['mse_approach']} / "
                   f"{v['mse_grasp']} / {v['mse_lift']} / {v['mse_first']} |")
  return "\n".join(lines)


def _savi_scores(row: Dict) -> str:
  """The table's FG-ARI cell: "-" without a SAVi, and its cube IoU and cube-found share where measured."""
  if not row.get("fg_ari"):
    return "-"
  if not row.get("cube_iou"):
    return row["fg_ari"]
  return f"{row['fg_ari']} (cube {row['cube_iou']}, found {float(row['cube_found']):.0%})"


def _readme(study: str) -> str:
  """The study's README text; a UserError where it is missing or lacks the markers of the generated table."""
  path = os.path.join(study, README_NAME)
  if not os.path.isfile(path):
    raise UserError(f"{path} not found: give a study's folder (one with a {README_NAME} holding the lines {BEGIN} "
                    f"and {END}, e.g. results/small/recipe).")
  with open(path) as f:
    text = f.read()
  if BEGIN not in text or END not in text:
    raise UserError(f"{path} lacks the markers of the generated table: add the lines {BEGIN} and {END}.")
  return text


def render(study: str) -> None:
  """Rewrites the README's generated block from the CSV (the README must hold both markers)."""
  head, rest = _readme(study).split(BEGIN, 1)
  _, tail = rest.split(END, 1)
  text = f"{head}{BEGIN}\n{table(read_rows(study))}\n{END}{tail}"
  fileio.atomic_write_text(os.path.join(study, README_NAME), text)


def keep_files(workdir: str, folder: str) -> List[str]:
  """Copies the files a probe's row is read from (KEPT, where present) from `workdir` to `folder`, in the same
  layout, so `probe_row(folder, ...)` gives the row again; returns the relative paths copied."""
  import shutil  # pylint: disable=import-outside-toplevel
  copied = []
  for rel in KEPT:
    source = os.path.join(workdir, rel)
    if os.path.exists(source):
      os.makedirs(os.path.dirname(os.path.join(folder, rel)), exist_ok=True)
      shutil.copyfile(source, os.path.join(folder, rel))
      copied.append(rel)
  return copied


def add(study: str, workdir: str, name: str) -> Dict:
  """Adds (or replaces) the probe `name` from `workdir`: its files in <study>/<name>/ (keep_files), its row in the
  CSV; then rebuilds the README's table. A study without a README fit for the table is refused before anything
  is written."""
  _readme(study)
  row = probe_row(workdir, name, read_baseline(study))
  keep_files(workdir, os.path.join(study, name))
  rows = [r for r in read_rows(study) if r["probe"] != name] + [row]
  write_rows(study, rows)
  render(study)
  return row


def main(argv) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
  parser.add_argument("study")
  parser.add_argument("workdir", nargs="?")
  parser.add_argument("--name")
  args = parser.parse_args(argv)
  try:
    if args.workdir:
      if not args.name:
        raise UserError("name the probe: --name NAME (its row in probes.csv).")
      print(add(args.study, args.workdir, args.name))
    else:
      render(args.study)
  except UserError as e:
    return errors.print_error(e)
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv[1:]))
