"""Success-rate tables in the paper's layout, as Markdown and LaTeX.

Rows are the generalization levels (the training distribution, printed "none" / "$\\emptyset$", then L1, L2, L3),
columns the encoders; each cell is "mean +- std" over evaluation seeds with two decimals, and the best mean of a row
is in bold (ties are all bold; a row whose best is 0.00 has no bold). A missing cell (an encoder that was skipped
or not evaluated at that level) prints as "-".

  cells = {("train", "savi"): (0.69, 0.06), ("L1", "savi"): (0.55, 0.02), ...}
  print(render_markdown(cells, encoders=("dino", "r3m", "savi")))
  print(render_latex(cells, encoders=("dino", "r3m", "savi"), caption="...", label="tab:push"))
"""
from typing import Dict, Mapping, Optional, Sequence, Tuple

from roboshape import encoders as registry
from roboshape.encoders import columns
from roboshape.envs.palettes import LEVEL_NAMES
from roboshape.errors import UserError

Cell = Optional[Tuple[float, float]]

_ROW_NAMES_MD = {"train": "none"}
_ROW_NAMES_TEX = {"train": r"$\emptyset$"}


def encoder_name(encoder: str) -> str:
  """The display name of a column, a registered encoder alone or with options (roboshape/encoders/columns.py:
  "savi" -> "SAVi", its Kind's title; "savi+proprio" -> "SAVi+proprio"); others as they are."""
  try:
    return columns.title(encoder)
  except UserError:
    return encoder


def level_name(level: str) -> str:
  """The display name of a level in Markdown and plots ("train" -> "none")."""
  return _ROW_NAMES_MD.get(level, level)


def sort_encoders(encoders: Sequence[str]) -> Tuple[str, ...]:
  """Columns in the registry's table order (roboshape.encoders.table_order: the paper's DINO, R3M, SAVi, with AE
  before SAVi and the controls after it), each encoder's columns with options right after its plain one in the
  given order, names the registry does not know after them in the given order."""
  order = registry.table_order()
  def base(name: str) -> str:
    return name.split(columns.SEPARATOR)[0]
  known = sorted((e for e in encoders if base(e) in order),
                 key=lambda e: (order.index(base(e)), e != base(e), list(encoders).index(e)))
  return tuple(known + [e for e in encoders if base(e) not in order])


def _best(cells: Mapping, level: str, encoders: Sequence[str]) -> set:
  """Encoders whose mean, rounded as printed, is the row's best (empty when the best is 0.00)."""
  means = {e: round(cells[(level, e)][0], 2) for e in encoders if cells.get((level, e)) is not None}
  if not means:
    return set()
  top = max(means.values())
  return {e for e, m in means.items() if m == top} if top > 0 else set()


def _rows(cells, encoders, levels):
  for level in levels:
    best = _best(cells, level, encoders)
    yield level, [(cells.get((level, e)), e in best) for e in encoders]


def _cell_texts(row, bold_format: str, cell_format: str) -> list:
  """Formats one table row's cells: "-" for a missing cell, else `cell_format` of (mean, std), the best in bold."""
  texts = []
  for cell, bold in row:
    if cell is None:
      texts.append("-")
    else:
      mean = f"{cell[0]:.2f}"
      texts.append(cell_format.format(bold_format.format(mean) if bold else mean, cell[1]))
  return texts


def render_markdown(cells: Mapping[Tuple[str, str], Cell], encoders: Sequence[str],
                    levels: Sequence[str] = LEVEL_NAMES) -> str:
  """A GitHub-Markdown table: header of encoders, one row per level, "**0.69** ± 0.06" cells."""
  lines = ["| | " + " | ".join(encoder_name(e) for e in encoders) + " |",
           "| --- |" + " --- |" * len(encoders)]
  for level, row in _rows(cells, encoders, levels):
    texts = _cell_texts(row, "**{}**", "{} ± {:.2f}")
    lines.append(f"| {level_name(level)} | " + " | ".join(texts) + " |")
  return "\n".join(lines) + "\n"


def render_latex(cells: Mapping[Tuple[str, str], Cell], encoders: Sequence[str], caption: str, label: str,
                 levels: Sequence[str] = LEVEL_NAMES) -> str:
  """A LaTeX `table` float with the paper's `|c||c|c|c|` tabular, "\\textbf{0.69} $\\pm$ 0.06" cells."""
  lines = [r"\begin{table}[h]", rf"\caption{{{caption}}}", rf"\label{{{label}}}", r"\begin{center}",
           r"\begin{tabular}{|c||" + "c|" * len(encoders) + "}", r"\hline",
           " & " + " & ".join(encoder_name(e) for e in encoders) + r" \\", r"\hline"]
  for level, row in _rows(cells, encoders, levels):
    texts = _cell_texts(row, r"\textbf{{{}}}", r"{} $\pm$ {:.2f}")
    lines.append(_ROW_NAMES_TEX.get(level, level) + " & " + " & ".join(texts) + r" \\")
    lines.append(r"\hline")
  lines += [r"\end{tabular}", r"\end{center}", r"\end{table}"]
  return "\n".join(lines) + "\n"


def cells_from_summary(summary: Sequence[Dict], task: str) -> Dict[Tuple[str, str], Cell]:
  """{(level, encoder): (mean, std)} of one task from summary rows ({task, encoder, level, mean, std, ...})."""
  return {(r["level"], r["encoder"]): (r["mean"], r["std"]) for r in summary
          if r["task"] == task and r.get("mean") is not None}


def render_milestones(rows: Sequence[Dict], names: Sequence[str]) -> str:
  """How far rollouts got (roboshape.report.results.milestone_counts rows): a Markdown table, one row per level, a
  column per milestone with the share of rollouts that reached it, then the same over the failed rollouts."""
  def share(k: int, n: int) -> str:
    return f"{k / n:.2f} ({k}/{n})" if n else "-"
  lines = ["| | rollouts | " + " | ".join(names) + " | failed | " + " | ".join(f"failed: {n}" for n in names) + " |",
           "| --- |" + " --- |" * (2 * len(names) + 2)]
  for r in rows:
    lines.append(f"| {level_name(r['level'])} | {r['rollouts']} | "
                 + " | ".join(share(r["reached"][n], r["rollouts"]) for n in names)
                 + f" | {r['failures']} | "
                 + " | ".join(share(r["failed_reached"][n], r["failures"]) for n in names) + " |")
  return "\n".join(lines) + "\n"
