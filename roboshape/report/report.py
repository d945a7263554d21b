"""The `report` stage: one table set for the runs of a grid (tasks x encoders), plus the overall figure.

For a grid config (configs/reproduce.py) the runs are <workdir>/<task>_<encoder>/; for a single experiment, the
workdir itself. Each run contributes its <run>/eval/results.json; a run that was skipped (a baseline whose
weights are absent: <run>/SKIPPED.json written by the grid) or that has no results yet appears in the report as a
"skipped: <reason>" line and as "-" cells, never as a crash.

`python -m roboshape.report.report RESULTS_ROOT` builds the same report over runs published one by one
(roboshape/report/publish.py: <root>/<task>_<encoder>/results.csv, e.g. results/small) into <root>/report/, and
rewrites the generated summary block of each published run's README.md from its results.csv and config.json
(roboshape/report/readme.py).

Outputs in <workdir>/report/: report.md, table_<task>.md and table_<task>.tex per task (mean ± std, the paper's
layout), success_by_level.png (success per level and encoder, a panel per task, with 95% intervals as error bars),
overall.png (mean success per encoder and level across tasks, the paper's overall figure), summary.json (the
summary rows and every interval) and results.csv (every rollout of every run). report.md holds, in order: the
verdict on the paper's two claims (roboshape/report/claims.py) and on the options beyond the paper, then per task the
table, each cell's success with its 95% interval (roboshape/report/stats.py), SAVi's success minus each other
encoder's, each column with options' success minus its plain encoder's, and each encoder's robustness to the shift
levels; then the core-hours of each cell and row (roboshape/report/compute.py); then the figures.
"""
import csv
import json
import os
import sys
from typing import Dict, List, Optional, Tuple

from roboshape import encoders as encoders_lib
from roboshape import errors
from roboshape import fileio
from roboshape import rundir
from roboshape.envs import TASKS
from roboshape.envs.palettes import LEVEL_NAMES
from roboshape.encoders import columns
from roboshape.errors import UserError
from roboshape.report import claims
from roboshape.report import compute
from roboshape.report import decompositions
from roboshape.report import paper
from roboshape.report import plots
from roboshape.report import publish
from roboshape.report import readme
from roboshape.report import results as results_lib
from roboshape.report import tables


def grid_runs(config, workdir: str) -> List[Tuple[str, str, str]]:
  """(task, column, run workdir) of every run the config covers (a single run's column: its encoder with the
  options its config turns on, roboshape/encoders/columns.py)."""
  if "grid" in config:
    return [(t, e, rundir.grid_run_dir(workdir, t, e)) for t in config.grid.tasks for e in config.grid.encoders]
  return [(config.task, columns.of_config(config), workdir)]


def load_run(task: str, encoder: str, run_dir: str) -> Dict:
  """{summary, rollouts, levels} of a run's evaluation, or {skipped: reason} when there is none."""
  skipped = os.path.join(run_dir, rundir.SKIPPED_FILE)
  if os.path.exists(skipped):
    with open(skipped) as f:
      return dict(skipped=json.load(f).get("reason", "skipped"))
  path = os.path.join(rundir.eval_dir(run_dir), rundir.RESULTS_FILE)
  if not os.path.exists(path):
    return dict(skipped=f"no evaluation results ({path} is missing: run its evaluate stage)")
  with open(path) as f:
    data = json.load(f)
  return dict(summary=[dict(r, task=task, encoder=encoder) for r in data["summary"]],
              rollouts=data["rollouts"], levels=data.get("levels", list(LEVEL_NAMES)),
              num_seeds=data.get("num_seeds"), rollouts_per_seed=data.get("rollouts_per_seed"))


def build_report(config, workdir: str) -> Dict[str, str]:
  """Writes the report files into <workdir>/report/; returns {name: path}."""
  runs = grid_runs(config, workdir)
  loaded = {(t, e): load_run(t, e, d) for t, e, d in runs}
  levels = list(config.eval.levels) if "eval" in config else list(LEVEL_NAMES)
  return write_report(runs, loaded, levels, rundir.report_dir(workdir))


def load_published(folder: str) -> Dict:
  """{task, encoder, summary, rollouts, levels, num_seeds, rollouts_per_seed} of a published run
  (roboshape/report/publish.py): its results.csv, one row per rollout, read back into rollout records."""
  path = os.path.join(folder, rundir.RESULTS_CSV)
  try:
    with open(path, newline="", encoding="utf-8") as f:
      rows = list(csv.DictReader(f))
    if not rows:
      raise UserError(f"{path} holds no rollouts: publish the run again once it is evaluated.")
    rollouts = [dict(r, train_seed=int(r["train_seed"]) if r.get("train_seed") else None,
                     seed_index=int(r["seed_index"]), rollout=int(r["rollout"]), seed=int(r["seed"]),
                     success=r["success"] == "True", length=int(r["length"])) for r in rows]
  except (ValueError, TypeError, KeyError, csv.Error) as e:    # not UTF-8, cut short, not roboshape's columns
    raise UserError(f"{path} is damaged ({type(e).__name__}): publish the run again from its workdir "
                    "(roboshape.report.publish.publish), or restore the file from git.") from None
  if "reached" in rows[0]:          # a CSV of a run evaluated before milestones were recorded has no such column
    for r in rollouts:
      r["reached"] = [m for m in (r["reached"] or "").split("+") if m]
  levels = {r["level"] for r in rollouts}
  return dict(task=rows[0]["task"], encoder=rows[0]["encoder"], summary=results_lib.summarize(rollouts),
              rollouts=rollouts, levels=[l for l in LEVEL_NAMES if l in levels],
              num_seeds=1 + max(r["seed_index"] for r in rollouts),
              rollouts_per_seed=1 + max(r["rollout"] for r in rollouts))


def published_config(folder: str) -> Dict:
  """A published run's config.json as a dict ({} when the folder has none)."""
  path = os.path.join(folder, "config.json")
  if not os.path.isfile(path):
    return {}
  with open(path) as f:
    return json.load(f)


def cell_block(folder: str) -> str:
  """The generated summary block (roboshape/report/readme.py) of the run published in `folder`, from its files."""
  return readme.block(load_published(folder), published_config(folder))


def build_published_report(root: str) -> Dict[str, str]:
  """The report over the runs published under `root` (<root>/<task>_<encoder>/results.csv, e.g. results/small),
  written into <root>/report/; every task x encoder pair without a published run is marked missing (with the
  cells of the grid that publishes there, publish.grid_record: not published yet, or skipped with its reason).
  Rewrites the summary block of each published run's README.md."""
  if not os.path.isdir(root):
    raise UserError(f"{root} is not a folder: give the folder runs are published to (e.g. results/small).")
  found, out_dir = {}, rundir.report_dir(root)
  for name in sorted(os.listdir(root)):
    if name == os.path.basename(out_dir):
      continue                      # this report's own output: its results.csv pools every run's rollouts
    if os.path.isfile(os.path.join(root, name, rundir.RESULTS_CSV)):
      run = load_published(os.path.join(root, name))
      found[(run["task"], run["encoder"])] = dict(run, folder=os.path.join(root, name))
  if not found:
    raise UserError(f"{root} holds no published run (<task>_<encoder>/{rundir.RESULTS_CSV}): publish one first "
                    "(configs/reproduce.py with grid.publish, or roboshape.report.publish).")
  datasets = publish.check_datasets({key: run["folder"] for key, run in found.items()})   # one per task, or nothing
  for run in found.values():       # every run read back before any README is rewritten
    readme.write(run["folder"], run, published_config(run["folder"]))
  grid = publish.grid_record(root)      # the publishing grid's cells: the missing ones are listed too
  named = {t for t, _ in found} | set(grid["tasks"])
  tasks = [t for t in TASKS if t in named] + sorted(named - set(TASKS))
  encoders = list(dict.fromkeys(list(grid["columns"]) + [e for _, e in found]))
  runs = [(t, e, os.path.join(root, rundir.grid_cell(t, e))) for t in tasks for e in encoders]

  def unpublished(cell):          # a cell of the grid without results: skipped (with the grid's reason) or pending
    reason = grid["skipped"].get(cell)
    return dict(skipped=reason) if reason is not None else dict(skipped="not published yet", pending=True)

  loaded = {(t, e): found.get((t, e)) or unpublished(rundir.grid_cell(t, e)) for t, e, _ in runs}
  return write_report(runs, loaded, list(LEVEL_NAMES), out_dir, datasets)


def write_report(runs: List[Tuple[str, str, str]], loaded: Dict[Tuple[str, str], Dict], levels: List[str],
                 out_dir: str, datasets: Optional[Dict[str, Dict[str, List[str]]]] = None) -> Dict[str, str]:
  """Writes report.md, the tables, overall.png, summary.json and results.csv of `runs` (task, encoder, folder),
  `loaded` holding each one's `load_run` (or `load_published`) result, into out_dir; returns {name: path}.
  datasets: the published cells' dataset identities ({task: {identity: [folders]}}, publish.check_datasets), listed
  under each task's table."""
  os.makedirs(out_dir, exist_ok=True)
  tasks = list(dict.fromkeys(t for t, _, _ in runs))
  encoders = tables.sort_encoders(list(dict.fromkeys(e for _, e, _ in runs)))
  levels = [l for l in LEVEL_NAMES if l in levels]
  summary = [row for r in loaded.values() if "summary" in r for row in r["summary"]]
  rollouts = [row for r in loaded.values() if "rollouts" in r for row in r["rollouts"]]
  sizes = {(r["num_seeds"], r["rollouts_per_seed"]) for r in loaded.values() if "summary" in r}

  paths = {}
  md = [f"# roboshape results: {', '.join(tasks)} x {', '.join(tables.encoder_name(e) for e in encoders)}", ""]
  if sizes:
    md.append("Cells: mean ± std (ddof=0) over evaluation seeds of the per-seed success rate; "
              + "; ".join(f"{s} seed(s) x {r} rollouts" for s, r in sorted(sizes, key=str))
              + ". \"none\" = the training distribution, L1 unseen distractor colours, L2 unseen background "
              "colours, L3 novel distractor sizes.")
    by_training = sorted({f"{r['task']} x {tables.encoder_name(r['encoder'])}" for r in summary
                          if results_lib.over_training_seeds([r])})
    if by_training:
      md.append(f"Cells of runs with several training seeds ({', '.join(by_training)}): mean ± std over the "
                "training seeds of each policy's success rate on all its evaluation rollouts.")
    md.append("")
  used = [o for o in columns.OPTIONS.values() if any(o.name in e.split(columns.SEPARATOR)[1:] for e in encoders)]
  if used:
    md += ["Options beyond the paper in these columns (roboshape/encoders/columns.py):", ""]
    md += [f"- `{columns.SEPARATOR}{o.name}`: {o.description}" for o in used] + [""]
  answer = claims.answer(loaded, tasks, encoders, levels)
  if answer.cells:
    md += [claims.METHOD, "", "## Verdict", "", claims.verdict(answer, tasks, encoders)]
  for task in tasks:
    cells = tables.cells_from_summary(summary, task)
    md_table = tables.render_markdown(cells, encoders, levels)
    tex = tables.render_latex(cells, encoders, levels=levels, label=f"tab:{task}",
                              caption=f"Success rate of \\textit{{{task}}} over the different generalization "
                                      "scenarios")
    paths[f"table_{task}.md"] = os.path.join(out_dir, f"table_{task}.md")
    paths[f"table_{task}.tex"] = os.path.join(out_dir, f"table_{task}.tex")
    fileio.atomic_write_text(paths[f"table_{task}.md"], md_table)
    fileio.atomic_write_text(paths[f"table_{task}.tex"], tex)
    md += [f"## {task}", "", md_table]
    pending = [tables.encoder_name(e) for e in encoders if loaded.get((task, e), {}).get("pending")]
    if pending:
      md.append(f"- not published yet: {', '.join(pending)}")
    published = sum(1 for (t, _), r in loaded.items() if t == task and r.get("folder"))
    for identity, folders in (datasets or {}).get(task, {}).items():
      md.append(f"- dataset: `{identity}` (its identity, a hash over the shards' checksums), recorded by "
                f"{len(folders)} of the {published} published cell(s) in their dataset.json")
    for encoder in encoders:
      r = loaded.get((task, encoder))
      if r is not None and "skipped" in r:
        if not r.get("pending"):
          md.append(f"- skipped: {tables.encoder_name(encoder)} on {task}: {r['skipped']}")
      elif r is not None:
        crashed = sum(row["crashed"] for row in r["summary"])
        if crashed:
          md.append(f"- {tables.encoder_name(encoder)} on {task}: {crashed} rollout(s) lost to simulator worker "
                    "crashes, left out of the rates.")
    if task in paper.TABLES:
      md += ["", f"The paper's {task} table ({paper.SOURCE[task]}):", "",
             tables.render_markdown(paper.TABLES[task], paper.ENCODERS, levels)]
      for encoder in paper.ENCODERS:
        r = loaded.get((task, encoder))
        if r is None or "skipped" in r:
          if r is None:
            why = ("not in this report's runs; the grid skips a baseline whose weights are absent"
                   if encoders_lib.get(encoder).baseline else "not in this report's runs")
          else:                     # a skipped cell's reason stands once, in its "- skipped:" line above
            why = r["skipped"] if r.get("pending") else f"skipped on {task}: its line above says why"
          md.append(f"- the paper's {tables.encoder_name(encoder)} column has no cell here ({why}).")
    md.append("")
    if any(t == task for t, _ in answer.cells):
      md += [f"### {task}: success with its 95% interval", "", claims.success_table(answer, task, encoders)]
    for title, table in ((f"### {task}: SAVi's success minus the others'", claims.pairs_table(answer, task, encoders)),
                         (f"### {task}: the options beyond the paper (a column's success minus its plain encoder's)",
                          claims.options_table(answer, task, encoders)),
                         (f"### {task}: robustness (success at a shift level / at the train level)",
                          claims.robustness_table(answer, task, encoders))):
      if table:
        md += [title, "", table]
  decomposed = decompositions.table([(t, e, f) for t, e, f in runs if "summary" in loaded.get((t, e), {})],
                                    tables.encoder_name)
  if decomposed:
    md += ["## Decompositions", "", "How the object-centric encoders decompose their task's validation frames at the "
           "end of pretraining (the selected seed's): FG-ARI and mIoU over every object, then, for the cube, the "
           "target (or bin) and the hand, the best IoU of any slot with the object's mask averaged over frames, and "
           "the share of frames where one slot covers the cube with IoU >= 0.5 (roboshape/report/decompositions.py;"
           " \"-\": validated before the measure existed).", ""] + decomposed + [""]
  md += ["## Compute", "", "Core-hours per cell and per task's row, from each run's stage log (stages.json: every "
         "attempt's wall time times the cores it held; roboshape/report/compute.py).", "",
         compute.render(runs, tasks, encoders)]
  if answer.success:
    paths["success_by_level.png"] = plots.levels_with_intervals(
        {k: (e.value, e.low, e.high) for k, e in answer.success.items()}, [t for t in tasks if any(
            k[0] == t for k in answer.success)], encoders, answer.levels, os.path.join(out_dir, "success_by_level.png"))
    md += ["## Success per level", "", "![success per level with 95% intervals](success_by_level.png)", "",
           f"Error bars: the 95% intervals of the tables above ({claims.ONE_SEED_MARK} there: one training seed); a "
           "dot on the axis: a success of 0 (no bar and no dot: no cell).", ""]
  if summary:
    paths["overall.png"] = plots.overall_bar_chart(summary, os.path.join(out_dir, "overall.png"), levels=levels)
    md += ["## Overall", "", "![overall success rate](overall.png)", ""]
    means, over = plots.overall_means(summary, levels), plots.overall_tasks(summary)
    md.append("| | " + " | ".join(tables.level_name(l) for l in levels) + " | mean over |")
    md.append("| --- |" + " --- |" * (len(levels) + 1))
    for encoder, values in means.items():
      md.append(f"| {tables.encoder_name(encoder)} | " + " | ".join(
          "-" if v != v else f"{v:.2f}" for v in values) + f" | {', '.join(over[encoder])} |")
    md.append("")
    if plots.tasks_differ(over):
      md += ["Each row averages the tasks it has a cell on (mean over); rows over different tasks are not comparable "
             "here: the per-task tables above compare them.", ""]
  else:
    md += ["No run has evaluation results yet.", ""]
  paths["summary.json"] = os.path.join(out_dir, "summary.json")
  fileio.atomic_write_json(paths["summary.json"], dict(
      runs=[dict(task=t, encoder=e, workdir=d, **({"skipped": loaded[(t, e)]["skipped"]}
                                                   if "skipped" in loaded[(t, e)] else {})) for t, e, d in runs],
      summary=summary,
      intervals=[dict(task=t, encoder=e, level=l, success=x.value, low=x.low, high=x.high, training_seeds=x.seeds[0])
                 for (t, e, l), x in answer.success.items()]), indent=1)
  paths["results.csv"] = os.path.join(out_dir, rundir.RESULTS_CSV)
  results_lib.write_csv(paths["results.csv"], rollouts)
  paths["report.md"] = os.path.join(out_dir, "report.md")
  fileio.atomic_write_text(paths["report.md"], "\n".join(md))
  return paths


def run(config, workdir: str) -> None:
  """The report stage: writes <workdir>/report/ and prints where it is."""
  paths = build_report(config, workdir)
  with open(paths["report.md"]) as f:
    print(f.read(), flush=True)
  print(f"[roboshape] report: {os.path.abspath(paths['report.md'])}", flush=True)


def main(argv) -> int:
  """python -m roboshape.report.report RESULTS_ROOT: the report over the runs published there."""
  if len(argv) != 2 or argv[1].startswith("-"):
    print("usage: python -m roboshape.report.report RESULTS_ROOT   (e.g. results/small)", file=sys.stderr)
    return 2
  try:
    paths = build_published_report(argv[1])
  except UserError as e:
    return errors.print_error(e)
  print(f"[roboshape] report: {os.path.abspath(paths['report.md'])}", flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main(sys.argv))
