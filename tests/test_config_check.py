"""The config check before the first stage (roboshape/config_check.py, roboshape/stages.py): bad input is one line.

Each bad input runs launch.py as a command with every stage of its config: a value the check missed would start
collecting, so the check must refuse it before that, with exit status 2, one `roboshape: error:` line naming the
field, no traceback, and the workdir as it was. The commands run in a launch.py kept warm (tests/warm_launch.py):
each is a process of its own, forked from one that has imported JAX once.
"""
import glob
import importlib
import os
import stat

import pytest

import warm_launch
from configs import common
from roboshape import rundir
from roboshape import stages
from roboshape.errors import UserError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SAVI = "--config=configs/pick_savi.py:tiny"

# (id, launch.py arguments, a text the error line must contain: the field it names)
BAD_CONFIGS = [
    ("unknown level", (SAVI, "--config.eval.levels=('L9',)"), "eval.levels"),
    ("no levels", (SAVI, "--config.eval.levels=()"), "eval.levels"),
    ("negative pretraining steps", (SAVI, "--config.pretrain.train.steps=-5"), "pretrain.train.steps"),
    ("no slots", (SAVI, "--config.savi.num_slots=0"), "savi.num_slots"),
    ("no policy history", (SAVI, "--config.policy.history=0"), "policy.history"),
    ("empty policy batches", (SAVI, "--config.policy.train.batch_size=0"), "policy.train.batch_size"),
    ("control history over the training one", (SAVI, "--config.policy.eval.history=11"), "policy.eval.history"),
    ("min distractors over max", (SAVI, "--config.env.min_distractors=5"), "env.min_distractors"),
    ("too many distractors", (SAVI, "--config.env.max_distractors=9"), "env.max_distractors"),
    ("a camera the scene has not", (SAVI, "--config.env.cameras=('front', 'top')"), "env.cameras"),
    ("unknown encoder", (SAVI, "--config.encoder=nope"), "encoder"),
    ("unknown stage", (SAVI, "--config.stages=('collect', 'fly')"), "stages"),
    ("pretrain without one", ("--config=configs/pick_r3m.py:tiny", "--config.stages=('collect', 'pretrain')"),
     "--config.stages"),
    ("unknown task", (SAVI, "--config.task=fly"), "task"),
    ("no training demos", (SAVI, "--config.data.train_episodes=0"), "data.train_episodes"),
    ("negative learning rate", (SAVI, "--config.policy.train.learning_rate=-1"), "policy.train.learning_rate"),
    ("no rollouts", (SAVI, "--config.eval.rollouts_per_seed=0"), "eval.rollouts_per_seed"),
    ("depth loss without depth", (SAVI, "--config.pretrain.train.depth_weight=0.5"), "pretrain.train.depth_weight"),
    ("decoder strides of another length", (SAVI, "--config.savi.decoder.strides=(2, 2)"), "savi.decoder.strides"),
    ("decoder output vs the frames", (SAVI, "--config.savi.decoder.grid_size=4"), "savi.decoder.grid_size"),
    ("a SAVi seed twice", (SAVI, "--config.pretrain.train_seeds=(1, 1)"), "pretrain.train_seeds"),
    ("a negative SAVi seed", (SAVI, "--config.pretrain.train_seeds=(0, -1)"), "pretrain.train_seeds"),
    ("seeds without validation to select by", (SAVI, "--config.pretrain.train_seeds=(0, 1)",
                                               "--config.pretrain.eval.episodes=0"), "pretrain.eval.episodes"),
    ("a key that moved", (SAVI, "--config.savi.train.steps=5"), "is now 'pretrain.train.steps'"),
    ("dropout over 1", (SAVI, "--config.policy.dropout=1.5"), "policy.dropout"),
    ("unknown R3M arch", ("--config=configs/pick_r3m.py:tiny", "--config.baselines.r3m.arch=resnet99"),
     "baselines.r3m.arch"),
    ("grid of an unknown encoder", ("--config=configs/reproduce.py:tiny", "--config.grid.encoders=('savi', 'nope')"),
     "grid.encoders"),
    ("grid run with a bad field", ("--config=configs/reproduce.py:tiny", "--config.policy.history=0"),
     "policy.history"),
    ("a skipped cell not in the grid", ("--config=configs/reproduce.py:tiny", "--config.grid.skip=('pick_savi',)"),
     "grid.skip"),
    ("grid column of an unknown option", ("--config=configs/reproduce.py:tiny",
                                          "--config.grid.encoders=('savi', 'savi+wings')"), "unknown option 'wings'"),
    ("an option turned on for a whole grid", ("--config=configs/reproduce.py:tiny", "--config.policy.proprio=True"),
     "--config.policy.proprio=True turns an option on for every column"),
    ("a SAVi pretrained elsewhere and here", (SAVI, "--config.pretrain.from_workdir=runs/pick_savi"),
     "pretrain.from_workdir"),
    ("a pretrained encoder from elsewhere for one without", ("--config=configs/pick_state.py:tiny",
                                                             "--config.pretrain.from_workdir=runs/pick_savi"),
     "pretrain.from_workdir"),
]


@pytest.fixture(scope="module")
def launch():
  """launch.py as a command: `launch(*args, workdir=...)` -> subprocess.CompletedProcess."""
  env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
  with warm_launch.WarmLaunch(cwd=ROOT, env=env) as server:
    yield lambda *args, workdir: server.run([*args, f"--workdir={workdir}"])


def _snapshot(path):
  """{relative path: bytes} of every file under `path` (None when it does not exist)."""
  if not os.path.exists(path):
    return None
  if os.path.isfile(path):
    with open(path, "rb") as f:
      return {"": f.read()}
  files = {}
  for root, _, names in os.walk(path):
    for name in names:
      full = os.path.join(root, name)
      with open(full, "rb") as f:
        files[os.path.relpath(full, path)] = f.read()
  return files


def _assert_refused(out, expected):
  assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
  lines = out.stderr.splitlines()
  assert len(lines) == 1, out.stderr[-2000:]
  assert lines[0].startswith("roboshape: error: "), lines[0]
  assert expected in lines[0], lines[0]
  assert "Traceback" not in out.stderr + out.stdout
  return lines[0]


@pytest.mark.parametrize("args, expected", [c[1:] for c in BAD_CONFIGS], ids=[c[0] for c in BAD_CONFIGS])
def test_a_bad_value_is_refused_before_any_stage_and_writes_nothing(launch, tmp_path, args, expected):
  workdir = tmp_path / "run"
  _assert_refused(launch(*args, workdir=workdir), expected)
  assert not workdir.exists()


def test_a_file_as_workdir_is_refused(launch, tmp_path):
  path = tmp_path / "notes.txt"
  path.write_text("mine\n")
  _assert_refused(launch(SAVI, workdir=path), "--workdir")
  assert path.read_text() == "mine\n"
  _assert_refused(launch(SAVI, workdir=path / "run"), "--workdir")
  assert path.read_text() == "mine\n"


def test_a_read_only_workdir_is_refused(launch, tmp_path):
  workdir = tmp_path / "locked"
  workdir.mkdir()
  (workdir / "keep.txt").write_text("kept\n")
  workdir.chmod(stat.S_IRUSR | stat.S_IXUSR)
  try:
    if os.access(workdir, os.W_OK):
      pytest.skip("permissions do not bind this user (root)")
    before = _snapshot(workdir)
    _assert_refused(launch(SAVI, workdir=workdir), "--workdir")
    assert _snapshot(workdir) == before
  finally:
    workdir.chmod(stat.S_IRWXU)


def test_a_workdir_of_another_run_is_refused_and_kept_byte_identical(launch, tmp_path):
  workdir = str(tmp_path / "push_r3m")
  rundir.save_config(common.get_config("push", "r3m", "tiny"), workdir)
  before = _snapshot(workdir)
  line = _assert_refused(launch(SAVI, workdir=workdir), "another --workdir")
  assert "task: 'push'" in line and "encoder: 'r3m'" in line
  assert _snapshot(workdir) == before
  # A grid's workdir is another run too.
  _assert_refused(launch("--config=configs/reproduce.py:tiny", workdir=workdir), "another --workdir")
  assert _snapshot(workdir) == before


def test_a_dataset_of_another_config_in_the_workdir_is_refused_before_config_json(tmp_path):
  from conftest import _synthetic_episode  # pylint: disable=import-outside-toplevel
  from roboshape import data  # pylint: disable=import-outside-toplevel
  from roboshape.data import collect, rlds  # pylint: disable=import-outside-toplevel
  # The workdir of a run of 3 train episodes (config.json and dataset); this config, of the same task, encoder
  # and variant, asks for 4.
  config = common.get_config("pick", "savi", "tiny")
  earlier = common.get_config("pick", "savi", "tiny")
  earlier.data.train_episodes = 3
  workdir = str(tmp_path / "pick_savi")
  rundir.save_config(earlier, workdir)
  summary = dict(collect.config_summary(earlier), resolution=16)
  rlds.write_dataset(data.dataset_path(config, workdir),
                     {"train": [_synthetic_episode(s, task="pick", state=True) for s in range(3)],
                      "val": [_synthetic_episode(1_000_000, task="pick", state=True)]}, summary)
  before = _snapshot(workdir)
  with pytest.raises(UserError, match=r"holds what the collect stage made with other settings "
                                       r"\(.*data.train_episodes: 3 there, 4 in this config\).*--redo=collect"):
    stages.run(config, workdir)
  assert _snapshot(workdir) == before       # config.json included: nothing was rewritten


def test_the_same_run_resumed_with_other_settings_rewrites_its_config(launch, tmp_path):
  workdir = str(tmp_path / "pick_savi")
  rundir.save_config(common.get_config("pick", "savi", "tiny"), workdir)
  out = launch(SAVI, "--config.stages=()", "--config.policy.train.steps=7", workdir=workdir)
  assert out.returncode == 0, out.stderr
  assert rundir.load_config(workdir).policy.train.steps == 7


def _shipped_configs():
  for path in sorted(glob.glob(os.path.join(ROOT, "configs", "*.py"))):
    name = os.path.basename(path)[:-3]
    if name in ("__init__", "common"):
      continue
    module = importlib.import_module(f"configs.{name}")
    for variant in common.VARIANTS:
      yield f"{name}:{variant}", module.get_config(variant)


def test_every_shipped_config_passes_the_check():
  names = []
  for name, config in _shipped_configs():
    stages.check(config)
    names.append(name)
  assert "reproduce:paper" in names and "pick_savi:small" in names and "push_ae:tiny" in names


def test_a_section_of_another_encoder_is_not_checked():
  config = common.get_config("pick", "r3m", "tiny")
  config.env.resolution = 32          # SAVi's decoder would not fit; R3M never builds it
  config.savi.num_slots = 0
  stages.check(config)
  config.baselines.r3m.input_size = 16
  with pytest.raises(UserError, match=r"baselines\.r3m\.input_size=16"):
    stages.check(config)


def test_an_unwritable_workdir_is_refused_before_config_json(tmp_path, monkeypatch):
  """The read-only case where chmod cannot bind (root): the permission check itself, with os.access saying no."""
  monkeypatch.setattr(stages.os, "access", lambda path, mode: False)
  config = common.get_config("pick", "savi", "tiny")
  config.stages = ()
  with pytest.raises(UserError, match=r"--workdir .* is not writable"):
    stages.run(config, str(tmp_path / "run"))
  assert not (tmp_path / "run").exists()
