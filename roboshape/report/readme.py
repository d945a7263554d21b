"""The generated summary block of a published cell's README (e.g. results/small/<task>_<encoder>/README.md).

A published cell (roboshape/report/publish.py) holds its rollouts in results.csv and the config that ran in
config.json; its README is written by hand. So that the README cannot quote a number those files do not hold, the
numbers live in a block between two markers that `python -m roboshape.report.report ROOT` rewrites from the files:

  <!-- summary:begin (generated from results.csv by roboshape.report.report) -->
  per level: success mean ± std (as table.md: over training seeds where the cell has several, else over evaluation
  seeds), successes / rollouts and each seed's count; the milestones reached at the train level; the dataset and
  the control setting config.json records
  <!-- summary:end -->

`write(folder, run, config)` replaces what is between the markers and nothing else, atomically; a README without
them gets them after its title line, and a folder without a README gets one. tests/test_results_readmes.py checks
that every committed block equals `render` of its folder's files.
"""
import os
import textwrap
from typing import Dict, List, Optional

from roboshape import envs
from roboshape import fileio
from roboshape.errors import UserError
from roboshape.report import results as results_lib
from roboshape.report import tables

BEGIN = "<!-- summary:begin (generated from results.csv by roboshape.report.report) -->"
END = "<!-- summary:end -->"
README = "README.md"
WIDTH = 118                         # the wrap of the block's sentences, as the hand-written READMEs wrap


def _count(rollouts: List[Dict]) -> str:
  finished = [r for r in rollouts if r["ended"] != "worker_crash"]
  return f"{sum(bool(r['success']) for r in finished)}/{len(finished)}"


def _seed_field(run: Dict) -> str:
  """The rollout field the cell's std is over: its training seed when it has several, else its evaluation seed."""
  return "train_seed" if results_lib.over_training_seeds(run["summary"]) else "seed_index"


def _what(run: Dict) -> str:
  """The sentence that says what the cell's rollouts are and what its mean ± std is over."""
  n, per, total = run["num_seeds"], run["rollouts_per_seed"], len(run["rollouts"])
  if _seed_field(run) == "train_seed":
    seeds = sorted({r["train_seed"] for r in run["rollouts"]})
    return (f"{total} rollouts: {len(seeds)} training seeds ({', '.join(map(str, seeds))}), each policy on {n} "
            f"evaluation seeds x {per} rollouts per level. Success: mean ± std (ddof=0) over the training seeds of "
            "each policy's rate on its rollouts of the level, as `table.md`.")
  return (f"{total} rollouts: one policy on {n} evaluation seeds x {per} rollouts per level. Success: mean ± std "
          "(ddof=0) over the evaluation seeds of each seed's rate, as `table.md`.")


def _level_rows(run: Dict) -> List[str]:
  field = _seed_field(run)
  per_seed = "per training seed" if field == "train_seed" else "per evaluation seed"
  lines = [f"| level | success | successes / rollouts | {per_seed} |", "| --- | --- | --- | --- |"]
  for row in run["summary"]:
    rollouts = [r for r in run["rollouts"] if r["level"] == row["level"]]
    seeds = sorted({r[field] for r in rollouts})
    counts = ", ".join(_count([r for r in rollouts if r[field] == s]) for s in seeds)
    success = "-" if row["mean"] is None else f"{row['mean']:.2f} ± {row['std']:.2f}"
    lines.append(f"| {tables.level_name(row['level'])} | {success} | {row['successes']}/{row['rollouts']} | "
                 f"{counts} |")
  return lines


def _milestones(run: Dict) -> str:
  """The milestones reached at the train level, pooled over seeds; or why there are none."""
  names = envs.MILESTONES.get(run["task"], ())
  if not any("reached" in r for r in run["rollouts"]):
    return "Milestones: not recorded (`results.csv` has no `reached` column)."
  counts = [c for c in results_lib.milestone_counts(run["rollouts"], names) if c["level"] == "train"]
  if not counts:
    return "Milestones: no rollout at the train level."
  c = counts[0]
  return (f"Milestones at the train level (rollouts that reached each at some step, of {c['rollouts']}): "
          + ", ".join(f"{n} {c['reached'][n]}" for n in names) + ".")


def _from_config(config: Optional[Dict]) -> List[str]:
  """The dataset and the control setting the run's config.json records (nothing when there is none)."""
  if not config:
    return []
  data, control = config.get("data", {}), config.get("policy", {}).get("eval", {})
  lines = []
  if "train_episodes" in data:
    where = f"`{data['dir']}`" if data.get("dir") else "the run's own `<workdir>/data`"
    lines.append(f"Dataset (`config.json`): {data['train_episodes']} training episodes (`data.train_episodes`) "
                 f"from `data.dir` {where}.")
  if control:
    lines.append(f"Control (`config.json` policy.eval): action `{control.get('action')}`, history "
                 f"{control.get('history')} (0: the training history).")
  return lines


def _wrap(text: str) -> str:
  return textwrap.fill(text, WIDTH, break_long_words=False, break_on_hyphens=False)


def render(run: Dict, config: Optional[Dict] = None) -> str:
  """The block's body for a published run (roboshape.report.report.load_published) and its config.json (a dict)."""
  crashed = sum(r["crashed"] for r in run["summary"])
  lines = [_wrap(f"**{run['task']} x {tables.encoder_name(run['encoder'])}, from this folder's files** "
                 "(`results.csv`, `config.json`; rewritten by `python -m roboshape.report.report` over the parent "
                 "folder: edit the files, not this block). " + _what(run)), ""]
  lines += _level_rows(run) + [""]
  if crashed:
    lines += [f"{crashed} rollout(s) lost to simulator worker crashes, left out of the rates.", ""]
  lines += [_wrap(line) for line in [_milestones(run)] + _from_config(config)]
  return "\n".join(lines) + "\n"


def block(run: Dict, config: Optional[Dict] = None) -> str:
  """The whole generated block, markers included."""
  return f"{BEGIN}\n{render(run, config)}{END}"


def current(text: str) -> Optional[str]:
  """The body between the markers of a README's text (None when it has no markers); UserError when they are
  broken (one without the other, out of order, or twice)."""
  if BEGIN not in text and END not in text:
    return None
  if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
    raise UserError(f"the summary markers are broken: keep one line {BEGIN} and after it one line {END}.")
  return text.split(BEGIN, 1)[1].split(END, 1)[0][1:]


def with_block(text: str, new_block: str) -> str:
  """`text` with its block replaced by `new_block`, or with `new_block` inserted after its first (title) line."""
  if current(text) is not None:
    head, rest = text.split(BEGIN, 1)
    return head + new_block + rest.split(END, 1)[1]
  title, newline, rest = text.partition("\n")
  return f"{title}\n\n{new_block}\n{rest}" if newline else f"{title}\n\n{new_block}\n"


def write(folder: str, run: Dict, config: Optional[Dict] = None) -> str:
  """Writes the block into <folder>/README.md (created with a title when missing), atomically; returns its path."""
  path = os.path.join(folder, README)
  if os.path.exists(path):
    with open(path) as f:
      text = f.read()
  else:
    text = f"# {run['task']} x {tables.encoder_name(run['encoder'])}\n"
  try:
    new = with_block(text, block(run, config))
  except UserError as e:
    raise UserError(f"{path}: {e}") from None
  if new != text:
    fileio.atomic_write_text(path, new)
  return path
