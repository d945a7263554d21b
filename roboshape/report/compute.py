"""What a grid's cells cost: core-hours per task x column and per task's row, from each run's stage log.

  compute.core_hours(folder)                 -> {stage: core-hours} of the run (or published run) in `folder`
  compute.render(runs, tasks, encoders)      -> the report's markdown table

The figures are the stage log's core-seconds (roboshape/rundir.py `read_stage_log`: every attempt's wall time
times the cores it held, a killed attempt up to its last beat), so a grid run on lanes counts each lane's one core
and a collection its whole machine. A task's dataset is collected once, in the stage log of the first of its runs
the grid ran (a dataset collected elsewhere and linked in shows as the few seconds the check took).
"""
from typing import Dict, Sequence, Tuple

from roboshape import rundir
from roboshape.report import tables


def core_hours(folder: str) -> Dict[str, float]:
  """{stage: core-hours} of the stage log in `folder` ({} when it has none)."""
  return {stage: rundir.logged_time(entry)[1] / 3600 for stage, entry in rundir.read_stage_log(folder).items()
          if isinstance(entry, dict)}


def render(runs: Sequence[Tuple[str, str, str]], tasks: Sequence[str], encoders: Sequence[str]) -> str:
  """A markdown table, one line per task: each column's core-hours (collection apart), the task's collection and
  the row's total; "-" where a cell has no stage log. `runs` are (task, column, folder)."""
  folders = {(t, e): d for t, e, d in runs}
  lines = ["| task | " + " | ".join(tables.encoder_name(e) for e in encoders) + " | collect | row |",
           "| --- |" + " --- |" * (len(encoders) + 2)]
  total = 0.0
  for task in tasks:
    cells, collect, row = [], 0.0, 0.0
    for encoder in encoders:
      hours = core_hours(folders[(task, encoder)]) if (task, encoder) in folders else {}
      collect += hours.pop("collect", 0.0)
      cells.append(f"{sum(hours.values()):.1f}" if hours else "-")
      row += sum(hours.values())
    row += collect
    total += row
    lines.append(f"| {task} | " + " | ".join(cells) + f" | {collect:.1f} | {row:.1f} |")
  return "\n".join(lines) + f"\n\n{total:.1f} core-hours in all.\n"
