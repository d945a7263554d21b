"""Every committed results README's numbers come from its files: the generated summary block of each published cell
(roboshape/report/readme.py, written by `python -m roboshape.report.report ROOT`) equals what its results.csv and
config.json give, and the tool rewrites that block and nothing else. The experiment configs point to those READMEs
and quote no result of their own."""
import ast
import csv
import json
import os
import re

import pytest

from configs import reproduce
from roboshape import grid
from roboshape.report import readme
from roboshape.report import report

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMALL = os.path.join(ROOT, "results", "small")
CELLS = sorted(name for name in os.listdir(SMALL)
               if name != "report" and os.path.isfile(os.path.join(SMALL, name, "results.csv")))
EXPERIMENTS = sorted(name[:-3] for name in os.listdir(os.path.join(ROOT, "configs"))
                     if re.fullmatch(r"(push|pick|place)_[a-z0-9]+\.py", name)) + ["reproduce"]
# what a quoted result looks like: a rate or score with two decimals, a count of rollouts, a date
RESULT = re.compile(r"(?<![\w.])[01]\.\d\d|\b\d+ of (60|180|240)\b|/(60|180|240)\b|\b20\d\d-\d\d-\d\d\b")
FIELDS = ("task", "encoder", "train_seed", "level", "seed_index", "rollout", "seed", "success", "length", "ended")


def test_the_published_cells_are_cells_of_the_small_grid():
  runs = {os.path.basename(d) for _, _, _, d in grid.grid_configs(reproduce.get_config("small"), "/w")}
  assert CELLS and set(CELLS) <= runs and "recipe" not in CELLS


@pytest.mark.parametrize("cell", CELLS)
def test_a_committed_readme_block_equals_what_its_results_csv_and_config_json_give(cell):
  folder = os.path.join(SMALL, cell)
  with open(os.path.join(folder, "README.md")) as f:
    text = f.read()
  body = readme.current(text)
  assert body is not None, f"{cell}/README.md has no summary block: run python -m roboshape.report.report results/small"
  assert f"{readme.BEGIN}\n{body}{readme.END}" == report.cell_block(folder), (
      f"{cell}/README.md's summary block is stale: run python -m roboshape.report.report results/small")
  assert text.index(readme.BEGIN) < text.index("\n\n") + 3      # right after the title line


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_an_experiment_config_gives_its_command_and_results_readme_in_a_few_lines_and_quotes_no_result(name):
  with open(os.path.join(ROOT, "configs", f"{name}.py")) as f:
    doc = ast.get_docstring(ast.parse(f.read()))
  assert f"python launch.py --config=configs/{name}.py" in doc
  readme_path = re.search(r"\nResults:  (\S+)", doc).group(1)
  # what it is in a line or two: runtimes and results live in generated files (reproduce says what the grid runs)
  assert name == "reproduce" or (len(doc.splitlines()) <= 4 and "Runtime" not in doc), (
      f"configs/{name}.py: a line or two, the command and where its results are; runtimes belong in {readme_path}")
  assert readme_path == ("results/small/README.md" if name == "reproduce" else f"results/small/{name}/README.md")
  # the README is there, or the config says it is not published yet (and stops saying so once it is)
  published = os.path.isfile(os.path.join(ROOT, readme_path))
  assert published != ("not published yet" in doc), (
      f"configs/{name}.py: {readme_path} is {'' if published else 'not '}there; its Results line should "
      f"{'not ' if published else ''}say \"not published yet\"")
  assert RESULT.search(doc) is None, f"configs/{name}.py quotes a result; it belongs in {readme_path}"


def _write_csv(folder, rows, reached=True):
  os.makedirs(folder, exist_ok=True)
  fields = FIELDS + (("reached",) if reached else ())
  with open(os.path.join(folder, "results.csv"), "w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)


def _rows(task, encoder, successes, train_seeds=("",), reached=""):
  """Two evaluation seeds x 2 rollouts at the train level and L1 per training seed; `successes` is the set of
  (train_seed, level, seed_index, rollout) that succeed."""
  return [dict(task=task, encoder=encoder, train_seed=t, level=level, seed_index=s, rollout=i, seed=s * 100 + i,
               success=str((t, level, s, i) in successes), length=9, ended="success", reached=reached)
          for t in train_seeds for level in ("train", "L1") for s in (0, 1) for i in (0, 1)]


def test_the_tool_adds_the_block_after_the_title_then_rewrites_only_the_block(tmp_path):
  root = str(tmp_path / "results")
  cell = os.path.join(root, "pick_savi")
  _write_csv(cell, _rows("pick", "savi", {("", "train", 0, 0), ("", "L1", 1, 1)}), reached=False)
  with open(os.path.join(cell, "README.md"), "w") as f:
    f.write("# pick x SAVi\n\nProse that stays, 0.99 and all.\n")
  assert report.main(["report", root]) == 0
  with open(os.path.join(cell, "README.md")) as f:
    text = f.read()
  assert text == f"# pick x SAVi\n\n{report.cell_block(cell)}\n\nProse that stays, 0.99 and all.\n"
  assert "| none | 0.25 ± 0.25 | 1/4 | 1/2, 0/2 |" in text and "per evaluation seed" in text
  assert "Milestones: not recorded (`results.csv` has no `reached` column)." in " ".join(text.split())
  assert "Dataset" not in text                                 # no config.json: nothing said about the data
  # The CSV changes (another success): the block follows it, the prose around it stays as it was.
  _write_csv(cell, _rows("pick", "savi", {("", "train", 0, 0), ("", "train", 1, 0), ("", "L1", 1, 1)}),
             reached=False)
  assert report.main(["report", root]) == 0
  with open(os.path.join(cell, "README.md")) as f:
    again = f.read()
  assert "| none | 0.50 ± 0.00 | 2/4 | 1/2, 1/2 |" in again
  assert again == f"# pick x SAVi\n\n{report.cell_block(cell)}\n\nProse that stays, 0.99 and all.\n"
  report.main(["report", root])
  with open(os.path.join(cell, "README.md")) as f:
    assert f.read() == again                                   # idempotent


def test_a_cell_with_training_seeds_milestones_and_a_config_says_all_of_them(tmp_path):
  root = str(tmp_path / "results")
  cell = os.path.join(root, "place_state")
  successes = {(0, "train", 0, 0), (1, "train", 0, 0), (1, "train", 1, 1), (1, "train", 0, 1)}
  _write_csv(cell, _rows("place", "state", successes, train_seeds=(0, 1), reached="grasped+lifted"))
  with open(os.path.join(cell, "config.json"), "w") as f:
    json.dump(dict(data=dict(dir="/runs/state_pp/data/place", train_episodes=200),
                   policy=dict(eval=dict(action="sample", history=1))), f)
  assert report.main(["report", root]) == 0                    # a folder without a README gets one
  with open(os.path.join(cell, "README.md")) as f:
    text = f.read()
  assert text.startswith(f"# place x State\n\n{readme.BEGIN}\n")
  # per training seed: 1/4 and 3/4, so 0.50 ± 0.25 over the training seeds (as table.md), 4 of 8 pooled
  assert "| none | 0.50 ± 0.25 | 4/8 | 1/4, 3/4 |" in text and "| L1 | 0.00 ± 0.00 | 0/8 | 0/4, 0/4 |" in text
  flat = " ".join(text.split())                                # the block's sentences are wrapped
  assert "Milestones at the train level (rollouts that reached each at some step, of 8): grasped 8, lifted 8, " \
         "over_bin 0, in_bin 0." in flat
  assert "200 training episodes (`data.train_episodes`) from `data.dir` `/runs/state_pp/data/place`" in flat
  assert "action `sample`, history 1" in flat and "mean ± std (ddof=0) over the training seeds" in flat


def test_broken_markers_are_a_one_line_error_and_leave_the_readme_alone(tmp_path, capsys):
  root = str(tmp_path / "results")
  cell = os.path.join(root, "push_ae")
  _write_csv(cell, _rows("push", "ae", set()))
  broken = f"# push x AE\n\n{readme.END}\nold\n{readme.BEGIN}\n"
  with open(os.path.join(cell, "README.md"), "w") as f:
    f.write(broken)
  assert report.main(["report", root]) == 2
  assert "summary markers are broken" in capsys.readouterr().err
  with open(os.path.join(cell, "README.md")) as f:
    assert f.read() == broken
