"""The probe study (roboshape/study.py): a row read from a run's files, and a README that equals its CSV."""
import csv
import json
import os

import pytest

from configs import common
from roboshape import study
from roboshape.errors import UserError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECIPE = os.path.join(ROOT, "results", "small", "recipe")


def _fake_run(workdir, variant="small", stored=None, **changes):
  """A run's files; `stored` {dotted field: value} is written into its config.json as it stands (e.g. a field
  today's configs no longer have)."""
  config = common.get_config("push", "objects", variant)
  for field, value in changes.items():
    common.override(config, f"{field}={value!r}")
  data = config.to_dict()
  for field, value in (stored or {}).items():
    *parents, leaf = field.split(".")
    node = data
    for key in parents:
      node = node[key]
    node[leaf] = value
  os.makedirs(os.path.join(workdir, "eval"))
  os.makedirs(os.path.join(workdir, "policy"))
  with open(os.path.join(workdir, "config.json"), "w") as f:
    json.dump(data, f)
  rows = [dict(task="push", encoder="objects", train_seed="", level=level, seed_index=0, rollout=i, seed=i,
               success=str(i < 3), length=10, ended="", reached="moved+halfway+on_target" if i < 3 else
               ("moved" if i == 3 else "")) for level in ("train", "L1") for i in range(5)]
  with open(os.path.join(workdir, "eval", "results.csv"), "w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
  with open(os.path.join(workdir, "policy", "val_metrics.json"), "w") as f:
    json.dump([dict(step=500, action_mse=0.09), dict(step=1000, action_mse=0.07), dict(step=1500, action_mse=0.08)],
              f)
  with open(os.path.join(workdir, "stages.json"), "w") as f:
    json.dump({"collect": {"seconds": 99.0, "cores": 2}, "cache": {"seconds": 5.0},      # a log before cores were kept
               "train_policy": {"seconds": 600.0, "core_seconds": 1200.0, "cores": 2},
               "evaluate": {"seconds": 115.0, "core_seconds": 230.0, "cores": 2}}, f)


def test_a_probe_row_reads_the_runs_files_and_names_only_what_changed(tmp_path):
  workdir = str(tmp_path / "run")
  _fake_run(workdir, **{"policy.history": 2, "data.dir": "/elsewhere", "eval.levels": ("train",)})
  row = study.probe_row(workdir, "h2")
  assert row["changed"] == "policy.history=2"          # data.dir and eval.levels are bookkeeping
  assert (row["rollouts"], row["successes"], row["success"]) == (5, 3, "0.60")   # the train level only
  assert row["reached"] == "moved 4 halfway 3 on_target 3"
  assert (row["val_mse_best"], row["best_step"], row["val_mse_last"]) == ("0.0700", 1000, "0.0800")
  assert (row["train_policy_s"], row["pretrain_s"], row["cores"]) == ("600", "", 2)
  assert row["core_hours"] == f"{(5 + 1200 + 230) / 3600:.2f}"    # collect left out; cache's old entry: one core


def test_a_removed_field_counts_as_changed_where_it_differs_from_the_default_it_had(tmp_path):
  # An old probe of the removed "_chunk" variant: its variant names the scale before the "_".
  removed = {"variant": "small_chunk", "policy.chunk": 8, "policy.eval.ensemble_decay": 0.01}
  _fake_run(str(tmp_path / "chunk"), stored=removed, **{"data.train_episodes": 2000})
  row = study.probe_row(str(tmp_path / "chunk"), "chunk", baseline={"*": {"data.train_episodes": 200}})
  assert (row["variant"], row["changed"]) == ("small_chunk", "data.train_episodes=2000; policy.chunk=8")
  _fake_run(str(tmp_path / "plain"), stored=dict(removed, variant="small", **{"policy.chunk": 1}))
  assert study.probe_row(str(tmp_path / "plain"), "plain")["changed"] == "(none)"


def test_a_field_of_a_section_only_other_encoders_read_is_no_change():
  savi = common.get_config("push", "savi", "small").to_dict()
  savi["ae"]["encoder"]["strides"] = [1, 1, 1, 1, 1]      # as rundir.upgrade_config copies an old run's savi section
  savi["savi"]["encoder"]["strides"] = [1, 1, 1, 1, 1]
  assert study.changed_fields(savi) == "savi.encoder.strides=(1, 1, 1, 1, 1)"
  ae = common.get_config("push", "ae", "small").to_dict()
  ae["savi"]["slot_size"] = 7                                 # the AE's token width when ae.latent_size=0
  ae["state"]["withhold"] = ["cube_quat"]
  assert study.changed_fields(ae) == "savi.slot_size=7"


def test_a_studys_baseline_replaces_todays_defaults_where_it_names_a_field_the_tasks_entries_over_stars(tmp_path):
  _fake_run(str(tmp_path / "run"), **{"data.train_episodes": 200, "policy.train.steps": 15000})
  config = json.load(open(tmp_path / "run" / "config.json"))
  assert study.changed_fields(config) == "data.train_episodes=200; policy.train.steps=15000"   # push: 2000, 5000
  assert study.changed_fields(config, {"*": {"data.train_episodes": 200}}) == "policy.train.steps=15000"
  both = {"*": {"data.train_episodes": 200, "policy.train.steps": 5000}, "push": {"policy.train.steps": 15000}}
  assert study.changed_fields(config, both) == ""
  assert study.changed_fields(config, dict(both, push={})) == "policy.train.steps=15000"
  (tmp_path / "study").mkdir()
  assert study.read_baseline(str(tmp_path / "study")) == {}
  (tmp_path / "study" / study.BASELINE_NAME).write_text(json.dumps(both))
  assert study.read_baseline(str(tmp_path / "study")) == both


def test_adding_probes_rewrites_the_csv_and_the_readme_block_only(tmp_path):
  study_dir = tmp_path / "study"
  study_dir.mkdir()
  (study_dir / "README.md").write_text(f"intro\n{study.BEGIN}\nold\n{study.END}\nafter\n")
  for name, history in (("a", 2), ("b", 3), ("a", 4)):       # a second "a" replaces the first
    workdir = str(tmp_path / f"run_{name}_{history}")
    _fake_run(workdir, **{"policy.history": history})
    study.add(str(study_dir), workdir, name)
  rows = study.read_rows(str(study_dir))
  assert [(r["probe"], r["changed"]) for r in rows] == [("b", "policy.history=3"), ("a", "policy.history=4")]
  text = (study_dir / "README.md").read_text()
  assert text.startswith("intro\n") and text.endswith("\nafter\n") and "old" not in text
  assert study.table(rows) in text
  assert sorted(os.listdir(study_dir / "a")) == ["config.json", "eval", "policy", "stages.json"]
  assert study.probe_row(str(study_dir / "a"), "a") == study.probe_row(str(tmp_path / "run_a_4"), "a")


def test_a_readme_without_markers_and_an_unevaluated_run_are_one_line_errors(tmp_path):
  (tmp_path / "README.md").write_text("no markers\n")
  with pytest.raises(UserError, match="lacks the markers"):
    study.render(str(tmp_path))
  assert (tmp_path / "README.md").read_text() == "no markers\n"
  with pytest.raises(UserError, match="config.json not found"):
    study.probe_row(str(tmp_path / "nothing"), "x")
  workdir = str(tmp_path / "run")
  _fake_run(workdir)
  os.remove(os.path.join(workdir, "eval", "results.csv"))
  with pytest.raises(UserError, match="evaluate the run first"):
    study.probe_row(workdir, "x")


def test_the_command_says_a_bad_input_in_one_line_as_every_tool_does(tmp_path, capsys):
  (tmp_path / "README.md").write_text("no markers\n")
  assert study.main([str(tmp_path), str(tmp_path / "run")]) == 2         # a probe without --name
  assert capsys.readouterr().err == "roboshape: error: name the probe: --name NAME (its row in probes.csv).\n"
  assert study.main([str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert err.startswith("roboshape: error: ") and "lacks the markers" in err and err.count("\n") == 1
  assert (tmp_path / "README.md").read_text() == "no markers\n"


def test_a_folder_without_a_study_readme_is_refused_before_anything_is_written(tmp_path, capsys):
  workdir = str(tmp_path / "run")
  _fake_run(workdir)
  for folder in (tmp_path / "absent", tmp_path / "empty"):
    if folder.name == "empty":
      folder.mkdir()
    assert study.main([str(folder)]) == 2
    assert study.main([str(folder), workdir, "--name", "x"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"roboshape: error: {folder / 'README.md'} not found: give a study's folder (one with a "
                   f"README.md holding the lines {study.BEGIN} and {study.END}, e.g. results/small/recipe)."] * 2
  assert not (tmp_path / "absent").exists() and os.listdir(tmp_path / "empty") == []
  (tmp_path / "empty" / "README.md").write_text("no markers\n")
  with pytest.raises(UserError, match="lacks the markers"):
    study.add(str(tmp_path / "empty"), workdir, "x")
  assert os.listdir(tmp_path / "empty") == ["README.md"]        # no probe files, no CSV


def test_the_committed_recipe_study_readme_equals_its_csv_and_the_csv_its_probes_files():
  rows = study.read_rows(RECIPE)
  assert rows, "results/small/recipe/probes.csv holds no probe"
  for row in rows:
    again = study.probe_row(os.path.join(RECIPE, row["probe"]), row["probe"], study.read_baseline(RECIPE))
    assert {k: str(v) for k, v in again.items()} == row
  with open(os.path.join(RECIPE, "README.md")) as f:
    text = f.read()
  block = text.split(study.BEGIN, 1)[1].split(study.END, 1)[0]
  assert block.strip() == study.table(rows)
