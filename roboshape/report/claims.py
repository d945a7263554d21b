"""The paper's two claims, answered from a report's cells with 95% intervals (roboshape/report/stats.py).

  Claim 1: an object-centric encoder (SAVi) succeeds more often than global ones (the family "global": DINO, R3M, AE).
  Claim 2: it loses less under distribution shift than they do.

`answer` estimates, per task: each encoder's success at each level; SAVi's success minus each other encoder's at
each level and averaged over the levels (paired: the two cells played the same start states); each encoder's
robustness, its success at a shift level (and averaged over the shift levels) divided by its success at the train
level; and SAVi's robustness minus each global encoder's. The tables render them; `verdict` reads the claims off
them, per task and global encoder, by which side of 0 the interval lies:

  claim 1: SAVi's success averaged over the levels minus the other's (each one's success beside it, the
  ground-truth object tokens' where that control ran: what a perfect decomposition reaches, and the privileged
  state's: what the behaviour cloning reaches at all); claim 2: SAVi's
  robustness over the shift levels (averaged) minus the other's.
  above 0: supports; below 0: contradicts; holding 0 or undefined: cannot decide, with how many more rollouts or
  training seeds would decide it if the difference held (stats.needed; beyond FAR times as many, only that
  bound), or why no number would.

A task supports a claim when every global encoder present there gives "supports", contradicts it when any gives
"contradicts", and cannot decide otherwise. A column with an option beyond the paper ("savi+proprio") is read the
same way against its plain encoder, paired on the same start states: the option helps, hurts or is not shown to
differ (`options_table`, the verdict's last paragraph). Every word of the verdict is computed from the cells.
"""
import dataclasses
import math
from typing import Dict, List, Sequence, Tuple

import numpy as np

from roboshape import encoders as registry
from roboshape.encoders import columns
from roboshape.errors import UserError
from roboshape.report import paper
from roboshape.report import stats
from roboshape.report import tables

# The encoders' parts in the claims come from the registry (roboshape.encoders.Kind.family): `object_centric()`
# the encoder under study, `global_encoders()` what the claims compare it with, `controls()` what the tables compare
# it with, not part of the claims, and `privileged()` the control that should succeed, named in claim 1.
LEVELS_MEAN = "mean"               # the column of a statistic averaged over the levels (or the shift levels)
OUTCOMES = {1: "supports", -1: "contradicts", 0: "cannot decide"}
OPTION_OUTCOMES = {1: "helps", -1: "hurts", 0: "not shown to differ"}
ONE_SEED_MARK = "†"
FAR = 100                          # beyond this factor the verdict gives no projection, only that it is beyond


@dataclasses.dataclass
class Answer:
  """Every estimate of a report, keyed by task.

  Attributes:
    success: {(task, encoder, level): Estimate}.
    pairs: {(task, other, level or LEVELS_MEAN): Estimate of SAVi's success minus `other`'s}.
    robustness: {(task, encoder, shift level or LEVELS_MEAN): Estimate}.
    gaps: {(task, other): Estimate of SAVi's robustness (LEVELS_MEAN) minus `other`'s}.
    options: {(task, column, level or LEVELS_MEAN): Estimate of a column with options beyond the paper's success
      minus its plain encoder's (`with_options`)}.
    cells: {(task, encoder): stats.Cell}.
    levels: the report's levels that some cell has.
    task_shifts: {task: the shift levels every cell of the task has}, which robustness averages over.
  """
  success: Dict[Tuple[str, str, str], stats.Estimate]
  pairs: Dict[Tuple[str, str, str], stats.Estimate]
  robustness: Dict[Tuple[str, str, str], stats.Estimate]
  gaps: Dict[Tuple[str, str], stats.Estimate]
  options: Dict[Tuple[str, str, str], stats.Estimate]
  cells: Dict[Tuple[str, str], stats.Cell]
  levels: Tuple[str, ...]
  task_shifts: Dict[str, Tuple[str, ...]]

  @property
  def shifts(self) -> Tuple[str, ...]:
    return tuple(l for l in self.levels if l != stats.TRAIN) if stats.TRAIN in self.levels else ()


def object_centric() -> str:
  return registry.in_family("object-centric")[0]


def global_encoders() -> Tuple[str, ...]:
  return registry.in_family("global")


def controls() -> Tuple[str, ...]:
  return registry.in_family("control")


def privileged() -> str:
  return registry.in_family("privileged")[0]


def compared(encoders: Sequence[str]) -> List[str]:
  """The encoders SAVi is compared with in the tables: the global ones, then the controls, as present."""
  return [e for e in global_encoders() + controls() if e in encoders]


def answer(loaded: Dict[Tuple[str, str], Dict], tasks: Sequence[str], encoders: Sequence[str],
           levels: Sequence[str], draws: int = stats.DRAWS, seed: int = stats.SEED) -> Answer:
  """Every estimate over `loaded` ({(task, encoder): a run with its `rollouts`, or skipped})."""
  cells = {(t, e): stats.cell(loaded[(t, e)]["rollouts"]) for t in tasks for e in encoders
           if "rollouts" in loaded.get((t, e), {}) and loaded[(t, e)]["rollouts"]}
  levels = [l for l in levels if any(l in c.levels for c in cells.values())]
  out = Answer({}, {}, {}, {}, {}, cells, tuple(levels), {})
  for task in tasks:
    out.task_shifts[task] = tuple(l for l in out.shifts if all(l in c.levels for (t, _), c in cells.items()
                                                                if t == task))
  for (task, encoder), c in cells.items():
    for level in levels:
      if level in c.levels:
        out.success[(task, encoder, level)] = stats.success(c, level, draws, seed)
    if stats.TRAIN in c.levels:
      for shift in out.shifts:
        if shift in c.levels:
          out.robustness[(task, encoder, shift)] = stats.robustness(c, [shift], draws, seed)
      if out.task_shifts[task]:
        out.robustness[(task, encoder, LEVELS_MEAN)] = stats.robustness(c, out.task_shifts[task], draws, seed)
  for task in tasks:
    savi = cells.get((task, object_centric()))
    for other in compared(encoders):
      c = cells.get((task, other))
      if savi is None or c is None:
        continue
      out.pairs.update({(task, other, l): e for l, e in _by_level(savi, c, levels, draws, seed).items()})
      if other in global_encoders() and out.task_shifts[task] and all(stats.TRAIN in x.levels for x in (savi, c)):
        out.gaps[(task, other)] = stats.robustness_difference(savi, c, out.task_shifts[task], draws, seed)
    for column, plain in with_options(encoders):
      c, base = cells.get((task, column)), cells.get((task, plain))
      if c is None or base is None:
        continue
      out.options.update({(task, column, l): e for l, e in _by_level(c, base, levels, draws, seed).items()})
  return out


def _by_level(a: stats.Cell, b: stats.Cell, levels: Sequence[str], draws: int, seed: int) -> Dict[str, stats.Estimate]:
  """{level: a's success minus b's} at each of `levels` both cells have, and at LEVELS_MEAN averaged over them."""
  common = [l for l in levels if l in a.levels and l in b.levels]
  out = {level: stats.difference(a, b, [level], draws, seed) for level in common}
  if common:
    out[LEVELS_MEAN] = stats.difference(a, b, common, draws, seed)
  return out


def with_options(encoders: Sequence[str]) -> List[Tuple[str, str]]:
  """(column, its plain encoder) for each column with options beyond the paper ("savi+proprio", "savi";
  roboshape/encoders/columns.py) whose plain encoder is a column too: what the option changes is read against it."""
  out = []
  for column in encoders:
    try:
      plain, fields = columns.parse(column)
    except UserError:
      continue
    if fields and plain in encoders:
      out.append((column, plain))
  return out


def _number(x: float, signed: bool) -> str:
  """Two decimals; three where two would print a number that is not 0 as 0 (an interval's bound just above 0)."""
  x = 0.0 if abs(x) <= stats.EPS else x
  digits = 3 if x != 0 and round(x, 2) == 0 else 2
  return f"{x:+.{digits}f}" if signed else f"{x:.{digits}f}"


def interval(e: stats.Estimate, signed: bool = False) -> str:
  """"0.13 [0.06, 0.22]" ("+0.10 [+0.04, +0.16]" signed), "1.33 [no interval]" where the interval is undefined,
  "undefined" where the value is; then the one-seed mark where a cell has one training seed."""
  if math.isnan(e.value):
    return "undefined"
  text = _number(e.value, signed) + (f" [{_number(e.low, signed)}, {_number(e.high, signed)}]" if e.defined
                                     else " [no interval]")
  return text + (ONE_SEED_MARK if e.one_seed else "")


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
  lines = ["| " + " | ".join(header) + " |", "| --- |" + " --- |" * (len(header) - 1)]
  lines += ["| " + " | ".join(row) + " |" for row in rows]
  return "\n".join(lines) + "\n"


def success_table(a: Answer, task: str, encoders: Sequence[str]) -> str:
  """Success per level (rows) and encoder (columns), pooled over the cell's rollouts, with its interval."""
  return _table([""] + [tables.encoder_name(e) for e in encoders],
                [[tables.level_name(l)] + [interval(a.success[(task, e, l)]) if (task, e, l) in a.success else "-"
                                           for e in encoders] for l in a.levels])


def _differences(a: Answer, rows: Sequence[Tuple[str, Dict[str, stats.Estimate]]]) -> str:
  """A table of differences, one row per (label, {level or LEVELS_MEAN: Estimate}) that has LEVELS_MEAN, per level
  and averaged over the levels ("" when none)."""
  body = [[label] + [interval(by_level[l], signed=True) if l in by_level else "-" for l in list(a.levels) +
                     [LEVELS_MEAN]] for label, by_level in rows if LEVELS_MEAN in by_level]
  if not body:
    return ""
  return _table([""] + [tables.level_name(l) for l in a.levels] + ["mean over levels"], body)


def pairs_table(a: Answer, task: str, encoders: Sequence[str]) -> str:
  """SAVi's success minus each compared encoder's, per level and averaged over the levels ("" when none)."""
  return _differences(a, [(f"SAVi − {tables.encoder_name(o)}", {l: e for (t, x, l), e in a.pairs.items()
                                                                if (t, x) == (task, o)}) for o in compared(encoders)])


def options_table(a: Answer, task: str, encoders: Sequence[str]) -> str:
  """Each column with options' success minus its plain encoder's, per level and averaged over the levels ("" when
  none)."""
  return _differences(a, [(f"{tables.encoder_name(c)} − {tables.encoder_name(p)}",
                           {l: e for (t, x, l), e in a.options.items() if (t, x) == (task, c)})
                          for c, p in with_options(encoders)])


def robustness_table(a: Answer, task: str, encoders: Sequence[str]) -> str:
  """Each encoder's robustness per shift level and over the shift levels, then SAVi's minus the global ones'."""
  columns = list(a.shifts) + [LEVELS_MEAN]
  rows = [[tables.encoder_name(e)] + [interval(a.robustness[(task, e, l)]) if (task, e, l) in a.robustness else "-"
                                      for l in columns]
          for e in encoders if (task, e, LEVELS_MEAN) in a.robustness]
  rows += [[f"SAVi − {tables.encoder_name(o)}"] + ["" for _ in a.shifts] + [interval(a.gaps[(task, o)], True)]
           for o in global_encoders() if (task, o) in a.gaps]
  if not rows:
    return ""
  return _table([""] + list(a.shifts) + ["mean over " + ", ".join(a.task_shifts[task])], rows)


def _needed(e: stats.Estimate) -> str:
  """What would decide an undecided difference: "; if the difference held, about ... would decide it", or why
  nothing would ("" for a decided or undefined one)."""
  if e.side != 0 or not e.defined:
    return ""
  if abs(e.value) <= stats.EPS:
    return "; the observed difference is 0, so no number of rollouts would decide it"
  n = stats.needed(e)
  if n is None:
    return ""
  if n.factor > FAR:
    # a difference under a tenth of its interval's half-width: a projection to a hundredfold rollouts and more
    # rests on an observed value that a few rollouts more or less would change, so only the bound is said
    return (f"; if the difference held, it would take more than {FAR} times "
            + ("the rollouts" if n.lower_bound else "both the rollouts and the training seeds") + " to decide it")
  ways = []
  if n.starts is not None:
    ways.append(f"about {n.starts} rollouts per level per training seed (now {e.starts}"
                + ("; at least, as the variation between training seeds is not counted" if n.lower_bound else "")
                + ")")
  if n.seeds is not None:
    ways.append(f"about {n.seeds} training seeds per cell (now {max(e.seeds)})")
  if not n.lower_bound:
    ways.append(f"{n.factor:.1f} times both the rollouts and the training seeds")
  if not ways:
    return ""
  return "; if the difference held, it would be decided with " + (
      ways[0] if len(ways) == 1 else ", ".join(ways[:-1]) + " or " + ways[-1])


def _never_succeeds(c: stats.Cell) -> bool:
  return not np.nansum(c.success) > 0


def _names(items: Sequence[str]) -> str:
  items = list(items)
  return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _level_mean(a: Answer, task: str, encoder: str, other: str) -> float:
  """The encoder's success averaged over the levels of SAVi's comparison with `other` on `task`: the average
  `stats.difference` takes of each cell for the pair's LEVELS_MEAN."""
  levels = [l for l in a.levels if (task, other, l) in a.pairs]
  return float(np.mean([a.success[(task, encoder, level)].value for level in levels]))


def _claim1(a: Answer, task: str, other: str) -> Tuple[int, str]:
  e, name = a.pairs[(task, other, LEVELS_MEAN)], tables.encoder_name(other)
  means = f"SAVi {_level_mean(a, task, object_centric(), other):.2f}, {name} {_level_mean(a, task, other, other):.2f}"
  text = f"{task}, SAVi − {name}: {interval(e, signed=True)} ({means} over the levels): {OUTCOMES[e.side]}"
  return e.side, text + _undecided(a, e, task, object_centric(), other)


def _undecided(a: Answer, e: stats.Estimate, task: str, first: str, second: str) -> str:
  """What would decide `e`, the difference between two cells of `task`, where its interval holds 0 ("" where it does
  not): no number of rollouts where neither cell ever succeeds, else `_needed`."""
  if e.side != 0:
    return ""
  if _never_succeeds(a.cells[(task, first)]) and _never_succeeds(a.cells[(task, second)]):
    return "; neither succeeds in any rollout, so no number of rollouts separates them"
  return _needed(e)


def _claim2(a: Answer, task: str, other: str) -> Tuple[int, str]:
  e, name = a.gaps[(task, other)], tables.encoder_name(other)
  text = f"{task}, SAVi − {name}: {interval(e, signed=True)}: {OUTCOMES[e.side]}"
  if e.defined:
    return e.side, text + _needed(e)
  why = []
  for encoder in (object_centric(), other):
    r = a.robustness[(task, encoder, LEVELS_MEAN)]
    if math.isnan(r.value):
      why.append(f"{tables.encoder_name(encoder)} never succeeds at the train level, so its robustness is undefined")
    elif not r.defined:
      why.append(f"{tables.encoder_name(encoder)}'s train-level success is 0 in {100 * r.undefined:.0f}% of the "
                 "resamples, so its robustness has no interval")
  if not why:
    why.append(f"one train-level success or the other is 0 in {100 * e.undefined:.0f}% of the resamples, so the "
               "difference has no interval")
  return 0, text + "; " + "; ".join(why) + ("; robustness can be compared only once the train level holds more "
                                             "successes than here (better policies, or many more rollouts)")


def _control(a: Answer, task: str) -> str:
  """Sentences on what the controls reach on `task` beside SAVi, "" without their cells: the ground-truth object
  tokens (the success an object-centric policy reaches from a perfect decomposition, against which SAVi's is read)
  and the privileged state (what the behaviour cloning and the closed loop reach at all, so that a difference
  between encoders is read beside how far both fall short of it), with the paper's SAVi over the same levels where
  the paper has them (a difference between failing policies reads otherwise than one between the paper's)."""
  text = []
  if (task, controls()[0], LEVELS_MEAN) in a.pairs:
    text.append(f"On {task} the ground-truth object tokens (the control) succeed "
                f"{_level_mean(a, task, controls()[0], controls()[0]):.2f} over the levels, SAVi − Objects "
                f"{interval(a.pairs[(task, controls()[0], LEVELS_MEAN)], signed=True)}.")
  levels = [l for l in a.levels if (task, privileged(), l) in a.success and (task, object_centric(), l) in a.success]
  if levels:
    state, savi = (float(np.mean([a.success[(task, e, l)].value for l in levels]))
                   for e in (privileged(), object_centric()))
    published = paper.TABLES.get(task, {})
    theirs = [published[(l, object_centric())][0] for l in levels if (l, object_centric()) in published]
    beside = f" (the paper's SAVi {np.mean(theirs):.2f})" if len(theirs) == len(levels) else ""
    text.append(f"The privileged state (the control that should succeed) succeeds {state:.2f} over the same "
                f"levels on {task}, SAVi {savi:.2f}{beside}.")
  return " ".join(text)


def _claim(a: Answer, tasks: Sequence[str], encoders: Sequence[str], number: int, title: str, judged: str,
           judge, keyed) -> str:
  """One claim's paragraph: its statement, how it is judged, a sentence per comparison, and what the table says per
  task."""
  present = [o for o in global_encoders() if o in encoders and any((t, o) in a.cells for t in tasks)]
  lines, by_task = [], {}
  for task in tasks:
    sides = []
    for other in present:
      if keyed(task, other):
        side, text = judge(a, task, other)
        sides.append(side)
        lines.append(text + ".")
    if sides:
      by_task[task] = -1 if -1 in sides else 1 if all(s == 1 for s in sides) else 0
  absent = [tables.encoder_name(o) for o in global_encoders() if o not in present]
  one_seed = [t for t in tasks if t in by_task and any(
      len(a.cells[(t, e)].train_seeds) == 1 for e in (object_centric(), *present) if (t, e) in a.cells)]
  text = [f"**Claim {number}: {title}**", judged] + lines
  if absent:
    judged_against = (f", so the claim is judged against {_names([tables.encoder_name(o) for o in present])} only"
                      if present else "")
    text.append(f"{_names(absent)}: no cell in this table (skipped or not run){judged_against}.")
  if one_seed:
    text.append(f"On {_names(one_seed)} a cell has one training seed ({ONE_SEED_MARK}): its interval leaves out the "
                "variation between training seeds.")
  if number == 1:
    text += [line for line in (_control(a, task) for task in by_task) if line]
  if not by_task:
    text.append(f"This table cannot decide claim {number}: it holds no SAVi cell beside a global encoder's"
                + (" with a train level" if number == 2 else "") + ".")
  else:
    groups = [(word, [t for t in tasks if by_task.get(t) == side]) for side, word in
              ((1, "supports"), (-1, "contradicts"), (0, "cannot decide"))]
    parts = [f"{word} {'claim ' + str(number) if i == 0 else 'it'} on {_names(ts)}"
             for i, (word, ts) in enumerate([g for g in groups if g[1]])]
    text.append(f"So this table {_names(parts)}.")
  return " ".join(text)


def _options(a: Answer, tasks: Sequence[str], encoders: Sequence[str]) -> str:
  """The paragraph on the options beyond the paper, "" without a column with options beside its plain one: per task,
  each such column's success averaged over the levels minus its plain encoder's, read by where its interval lies."""
  lines = []
  for task in tasks:
    for column, plain in with_options(encoders):
      if (task, column, LEVELS_MEAN) not in a.options:
        continue
      e = a.options[(task, column, LEVELS_MEAN)]
      lines.append(f"{task}, {tables.encoder_name(column)} − {tables.encoder_name(plain)}: "
                   f"{interval(e, signed=True)}: {OPTION_OUTCOMES[e.side]}{_undecided(a, e, task, column, plain)}.")
  if not lines:
    return ""
  return " ".join(["**Options beyond the paper** (not a claim of the paper: what each option changes for its "
                   "encoder). Judged per task on the column's success averaged over the levels minus its plain "
                   "encoder's, by where its 95% interval lies:"] + lines)


def verdict(a: Answer, tasks: Sequence[str], encoders: Sequence[str]) -> str:
  """The generated verdict: a paragraph per claim, then one on the options beyond the paper where the table has
  them (Markdown)."""
  claim1 = _claim(a, tasks, encoders, 1, "an object-centric encoder (SAVi) succeeds more often than global ones.",
                  "Judged per task on SAVi's success averaged over the levels minus the other's, by where its 95% "
                  "interval lies:", _claim1, lambda t, o: (t, o, LEVELS_MEAN) in a.pairs)
  claim2 = _claim(a, tasks, encoders, 2, "it loses less under distribution shift.", "Judged per task on SAVi's "
                  "robustness (its success averaged over the shift levels divided by its success at the train "
                  "level) minus the other's, by where its 95% interval lies:", _claim2,
                  lambda t, o: (t, o) in a.gaps)
  options = _options(a, tasks, encoders)
  return claim1 + "\n\n" + claim2 + "\n" + ("\n" + options + "\n" if options else "")


METHOD = ("Intervals: 95% percentile intervals of a hierarchical bootstrap (roboshape/report/stats.py, "
          f"{stats.DRAWS} resamples, seed {stats.SEED}): a cell's training seeds are drawn first, then its start "
          "states (env seeds), one draw for every training seed, every level and both cells of a comparison, "
          "since they all played the same start states. Success is pooled over the cell's rollouts. "
          f"{ONE_SEED_MARK}: a cell with one training seed, whose interval leaves out the variation between "
          "training seeds. Robustness: success at a shift level divided by success at the train level; "
          "\"undefined\" where the train level has no success, \"no interval\" where more than 2.5% of the "
          "resamples have none.")
