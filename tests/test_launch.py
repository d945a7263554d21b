"""launch.py: config variants, command-line overrides, and one-line errors for bad input."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from configs import common
from roboshape import encoders
from roboshape import stages
from roboshape.errors import UserError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _launch(*args, workdir=None):
  cmd = [sys.executable, "launch.py", *args]
  if workdir:
    cmd.append(f"--workdir={workdir}")
  return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)


def test_overrides_reach_the_saved_config(tmp_path):
  out = _launch("--config=configs/pick_savi.py:tiny", "--config.stages=()", "--config.policy.train.steps=7",
                "--config.env.resolution=32", workdir=str(tmp_path))
  assert out.returncode == 0, out.stderr
  saved = json.loads((tmp_path / "config.json").read_text())
  assert saved["policy"]["train"]["steps"] == 7
  assert saved["env"]["resolution"] == 32
  assert saved["task"] == "pick" and saved["encoder"] == "savi" and saved["variant"] == "tiny"


def test_unknown_key_names_the_valid_keys_near_it(tmp_path):
  out = _launch("--config=configs/pick_savi.py:tiny", "--config.policy.train.stepz=3", workdir=str(tmp_path))
  assert out.returncode == 2
  lines = out.stderr.strip().splitlines()
  assert len(lines) == 1, out.stderr
  assert "unknown config key 'policy.train.stepz'" in lines[0]
  assert "policy.train.steps" in lines[0]
  assert not (tmp_path / "config.json").exists()


@pytest.mark.parametrize("args, expected", [
    (("--config=configs/pick_savi.py:huge",), "unknown variant 'huge'"),
    (("--config=configs/nope.py",), "config file 'configs/nope.py' not found"),
    (("--config=configs/pick_savi.py:tiny", "--config.seed=abc"), "bad command-line flag"),
    (("--config=configs/pick_savi.py:tiny", "--config.stages=('collect', 'fly')"), "unknown stage(s) fly"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, expected):
  out = _launch(*args, workdir=str(tmp_path))
  assert out.returncode == 2
  assert out.stderr.count("\n") == 1 and expected in out.stderr, out.stderr
  assert "Traceback" not in out.stderr


def test_variants_scale_the_experiment():
  sizes = {v: common.get_config("push", "savi", v).data.train_episodes for v in common.VARIANTS}
  assert sizes["paper"] == sizes["small"] == 2000 and sizes["tiny"] < sizes["small"]   # the recipe's demos
  steps = {t: common.get_config(t, "objects", "small").policy.train.steps for t in common.TASKS}
  assert steps == {"push": 5000, "pick": 5000, "place": 15000}        # TASK_SMALL_STEPS, at :small only
  assert common.get_config("place", "objects", "paper").policy.train.steps == 100_000
  assert "pretrain" not in common.get_config("push", "dino", "tiny").stages
  assert "pretrain" in common.get_config("push", "savi", "tiny").stages


def test_every_experiment_config_loads():
  for task in common.TASKS:
    for encoder in encoders.names():
      path = os.path.join(ROOT, "configs", f"{task}_{encoder}.py")
      namespace = {}
      with open(path) as f:
        exec(compile(f.read(), path, "exec"), namespace)  # pylint: disable=exec-used
      config = namespace["get_config"]("tiny")
      assert (config.task, config.encoder) == (task, encoder)


def test_place_policies_are_run_with_a_sampled_mode_and_one_frame_whatever_the_encoder():
  for encoder in encoders.names():
    for variant in common.VARIANTS:
      place = common.get_config("place", encoder, variant).policy.eval
      assert (place.action, place.history) == ("sample", 1)
      for task in ("push", "pick"):
        control = common.get_config(task, encoder, variant).policy.eval
        assert (control.action, control.history) == ("mean", 0)


@pytest.mark.parametrize("args, expected", [
    (("--config=configs/push_objects.py:small_chunk",),
     "unknown variant 'small_chunk'; use configs/<exp>.py:<variant> with one of paper, small, tiny."),
    (("--config=configs/push_objects.py:small", "--config.policy.chunk=8"),
     "config key 'policy.chunk' was removed: action chunking lost its comparison (results/small/recipe/README.md); "
     "drop --config.policy.chunk\n"),
])
def test_action_chunking_asked_for_is_one_line_and_exit_2(tmp_path, args, expected):
  out = _launch(*args, "--config.stages=()", workdir=str(tmp_path))
  assert out.returncode == 2
  assert out.stderr.count("\n") == 1 and expected in out.stderr, out.stderr
  assert not os.listdir(tmp_path)


def test_a_run_trained_with_action_chunks_is_not_resumed_and_its_config_is_kept(tmp_path):
  workdir = tmp_path / "old"
  workdir.mkdir()
  chunked = os.path.join(ROOT, "results", "small", "recipe", "push_objects_2000_chunk", "config.json")
  shutil.copy(chunked, workdir / "config.json")
  before = (workdir / "config.json").read_bytes()
  config = common.get_config("push", "objects", "small")
  config.stages = ()
  with pytest.raises(UserError, match=r"old/config.json is a run trained with action chunks \(policy.chunk=8\), "
                     r"which this roboshape no longer has: action chunking lost its comparison"):
    stages.run(config, str(workdir))
  assert sorted(os.listdir(workdir)) == ["config.json"] and (workdir / "config.json").read_bytes() == before


def test_override_sets_a_nested_field_from_a_python_literal():
  config = common.get_config("push", "savi", "tiny")
  common.override(config, "savi.decoder.strides=(2, 2)")
  common.override(config, "pretrain.train.learning_rate=1e-3")
  assert tuple(config.savi.decoder.strides) == (2, 2) and config.pretrain.train.learning_rate == 1e-3
  with pytest.raises(KeyError):
    common.override(config, "savi.no_such_field.x=1")


def test_host_devices_one_per_core_of_the_process(monkeypatch):
  from roboshape import cli  # pylint: disable=import-outside-toplevel
  monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3, 5})
  monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
  assert cli.host_device_per_core() == 3
  assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_enable_fast_math=false",
                                             "--xla_force_host_platform_device_count=3"]
  monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")    # the user's count is kept
  assert cli.host_device_per_core() == 1
  assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
  # a grid lane replaces the count it inherited with its own cores'
  monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2 --xla_cpu_enable_fast_math=false")
  monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {1})
  assert cli.host_device_per_core(override=True) == 1
  assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_enable_fast_math=false",
                                             "--xla_force_host_platform_device_count=1"]


def test_a_config_json_from_before_the_pretrain_section_reads_in_todays_fields(tmp_path):
  """A config.json of the former :small table (push x AE's, kept in tests/fixtures) holds SAVi's training settings in
  savi.train/savi.eval and the AE's frame model nowhere: read back (rundir.load_config), it has today's fields with
  their values, and the study finds no change against today's :small defaults but the recipe adopted since (200
  demos then, 2000 now; no frame pool; the plain reconstruction loss; a field it predates whose default has not
  changed, such as policy.proprio, is none)."""
  import shutil  # pylint: disable=import-outside-toplevel
  from roboshape import rundir  # pylint: disable=import-outside-toplevel
  from roboshape import study  # pylint: disable=import-outside-toplevel
  fixture = os.path.join(ROOT, "tests", "fixtures", "config_before_pretrain_section.json")
  with open(fixture) as f:
    old = json.load(f)
  shutil.copy(fixture, tmp_path / rundir.CONFIG_FILE)
  config = rundir.load_config(str(tmp_path))
  assert config.pretrain.train.steps == old["savi"]["train"]["steps"] == 8000
  assert tuple(config.pretrain.train_seeds) == tuple(old["savi"]["train"]["seeds"])
  assert (config.pretrain.train.clip_norm, config.pretrain.train.clip_norm_of) == (0.05, "mean")
  assert config.pretrain.eval.frames == old["savi"]["eval"]["frames"] and "train" not in config.savi
  assert config.ae.encoder.to_dict() == old["savi"]["encoder"] and config.ae.pool == old["savi"]["pool"]
  # the fields it predates read as the run ran (rundir.ADDED): those whose :small default changed since are changes
  assert "frame_pool" not in old["policy"] and config.policy.frame_pool is False
  assert "pretrain" not in old and config.pretrain.train.mask_weight == 0.0
  assert study.changed_fields(config.to_dict()) == ("data.train_episodes=200; policy.frame_pool=False; "
                                                    "pretrain.train.mask_weight=0.0")
  today = common.get_config("push", "ae", "small").to_dict()
  assert rundir.upgrade_config(today) == today                        # today's configs come back as they are


def _flat_keys(tree, prefix=""):
  return {k for key, value in tree.items()
          for k in (_flat_keys(value, f"{prefix}{key}.") if isinstance(value, dict) and value else {prefix + key})}


def test_every_saved_config_reads_back_with_every_field_of_todays_configs(tmp_path):
  """Every config.json on file (the old fixture, each published run's) reads back through rundir.ADDED with every
  field today's config of its experiment has, so code reads no default of its own; a field added to
  configs/common.py without its entry in ADDED fails here. Read back, its fields keep the values saved."""
  import glob  # pylint: disable=import-outside-toplevel
  import shutil  # pylint: disable=import-outside-toplevel
  from roboshape import rundir  # pylint: disable=import-outside-toplevel
  paths = [os.path.join(ROOT, "tests", "fixtures", "config_before_pretrain_section.json")] + sorted(
      glob.glob(os.path.join(ROOT, "results", "small", "*", rundir.CONFIG_FILE)))
  assert len(paths) > 10
  for path in paths:
    shutil.copy(path, tmp_path / rundir.CONFIG_FILE)
    config = rundir.load_config(str(tmp_path)).to_dict()
    today = common.get_config(config["task"], config["encoder"], config["variant"].partition("_")[0]).to_dict()
    missing = _flat_keys(today) - _flat_keys(config)
    assert not missing, (path, sorted(missing))
    with open(path) as f:
      saved = json.load(f)
    if "pretrain" in saved:                                     # written after the last renaming
      assert {k: config["policy"]["train"][k] for k in saved["policy"]["train"]} == saved["policy"]["train"]
      assert all(config["policy"].get(k) == v for k, v in saved["policy"].items() if k != "train" and
                 not isinstance(v, list))


def test_a_policy_record_from_before_a_field_compares_as_the_value_it_ran_with(tmp_path):
  """A policy's fingerprint.json written before policy.frame_pool existed: a rerun asking for the frame pool differs
  from it (the policy ran without one), said in one line with both values; a rerun without it resumes."""
  from roboshape import rundir  # pylint: disable=import-outside-toplevel
  from roboshape.train import fingerprint  # pylint: disable=import-outside-toplevel
  config = common.get_config("push", "state", "tiny")
  workdir = str(tmp_path)
  folder = rundir.policy_dir(workdir)
  record = {k: v for k, v in fingerprint.fingerprint(config, "train_policy").items() if k != "policy.frame_pool"}
  os.makedirs(folder)
  with open(rundir.fingerprint_path(folder), "w") as f:
    json.dump({"stage": "train_policy", "fields": record}, f)
  with open(os.path.join(folder, "checkpoint"), "w") as f:
    f.write("held")
  assert fingerprint.check(config, workdir).set_aside == {}            # False then, False now: the same
  config.policy.frame_pool = True
  with pytest.raises(UserError, match=r"policy\.frame_pool: False there, True in this config"):
    fingerprint.check(config, workdir)
