"""The tools that read a run's files say which file is damaged, in one line with exit status 2, and leave it be; a
full disk is found wherever a library noticed it, and a small write it stops leaves the file as it was."""
import errno
import json
import os

import pytest

from configs import common
from roboshape import fileio
from roboshape import rundir
from roboshape import status
from roboshape.errors import UserError
from roboshape.report import report

GOOD_ROW = ("task,encoder,train_seed,level,seed_index,rollout,seed,success,length,ended,reached\n"
            "push,state,,train,0,0,1000000000,True,20,success,moved+halfway+on_target\n")


def _run(tmp_path):
  workdir = str(tmp_path / "run")
  rundir.save_config(common.get_config("push", "state", "tiny"), workdir)
  return workdir


def test_a_config_json_that_is_not_json_is_one_line_naming_it(tmp_path, capsys):
  workdir = _run(tmp_path)
  path = os.path.join(workdir, rundir.CONFIG_FILE)
  for damage in (b"{\"task\": \"pu", b"\xff\xfe\x00garbage", b"[1, 2]"):
    with open(path, "wb") as f:
      f.write(damage)
    with pytest.raises(UserError, match=f"{path} is damaged .*restore it") as e:
      rundir.load_config(workdir)
    assert "\n" not in str(e.value) and "delet" in str(e.value)     # the safe action, not a deletion
    assert status.main(["status", workdir]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "config.json is damaged" in err
    assert open(path, "rb").read() == damage                         # left as it was


def test_status_says_a_damaged_stage_log_is_damaged_rather_than_pending(tmp_path, capsys):
  workdir = _run(tmp_path)
  rundir.record_stage(workdir, "collect", "done", 3.0)
  assert status.main(["status", workdir]) == 0
  assert "pending" in capsys.readouterr().out
  with open(rundir.stage_log_path(workdir), "w") as f:
    f.write("{\"collect\": {\"state\": ")
  assert status.main(["status", workdir]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and "stages.json is damaged" in err
  assert rundir.read_stage_log(workdir) == {}                      # a run itself starts the log afresh


@pytest.mark.parametrize("content", [os.urandom(512), GOOD_ROW[:70], GOOD_ROW + "push,state,,train,0,1\n",
                                     "a,b\n1,2\n"])
def test_report_over_a_damaged_published_csv_is_one_line_naming_it(tmp_path, capsys, content):
  cell = tmp_path / "push_state"
  cell.mkdir()
  (cell / "results.csv").write_bytes(content if isinstance(content, bytes) else content.encode())
  before = (cell / "results.csv").read_bytes()
  assert report.main(["report", str(tmp_path)]) == 2
  err = capsys.readouterr().err
  assert err.count("\n") == 1 and f"{cell / 'results.csv'}" in err
  assert (cell / "results.csv").read_bytes() == before


def test_a_missing_checkpoints_hint_names_the_runs_variant(tmp_path):
  import roboshape  # pylint: disable=import-outside-toplevel
  workdir = str(tmp_path / "run")
  rundir.save_config(common.get_config("push", "savi", "tiny"), workdir)
  with pytest.raises(UserError, match=r"run the pretrain stage first \(python launch.py "
                     rf"--config=configs/push_savi.py:tiny --workdir={workdir}\)"):
    roboshape.load_encoder(workdir)
  assert sorted(os.listdir(workdir)) == ["config.json"]             # a loader creates no empty checkpoint folder


def test_a_data_dir_the_run_cannot_write_is_refused_before_anything_is_written(tmp_path, monkeypatch):
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  data = tmp_path / "readonly_data"
  data.mkdir()
  real_access = os.access
  monkeypatch.setattr(os, "access", lambda path, mode: False if str(path) == str(data) else real_access(path, mode))
  config = common.get_config("push", "state", "tiny")
  config.data.dir = str(data)
  workdir = tmp_path / "run"
  with pytest.raises(UserError, match=r"--config.data.dir .* is not writable .*read-only file system"):
    stages.run(config, str(workdir))
  assert not workdir.exists() and not os.listdir(data)
  config.stages = ("train_policy",)        # a run that does not collect only reads the dataset: no such check
  stages.check_workdir(config, str(workdir))


def _raised(fail):
  try:
    fail()
  except Exception as e:  # pylint: disable=broad-except
    return e
  raise AssertionError("nothing raised")


def test_a_full_disk_is_found_in_whatever_error_a_library_wraps_it_and_names_its_path():
  def orbax():             # TensorStore's error as orbax raises it, while a Python write's ENOSPC was being handled
    try:
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    except OSError:
      raise ValueError('RESOURCE_EXHAUSTED: Error writing "b/0" in OCDBT database at local file '
                       '"/w/savi/checkpoints/20.orbax-checkpoint-tmp/state/": Failed to write 183 bytes to file 8: '
                       "No space left on device [os_error_code='28']") from None

  def wrapped():           # a bare ENOSPC (a Python write names no file) under another error type
    try:
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    except OSError as e:
      raise RuntimeError("save failed") from e

  e = _raised(orbax)
  assert fileio.disk_full(e) and fileio.disk_full_path(e) == "/w/savi/checkpoints/20.orbax-checkpoint-tmp/state/"
  e = _raised(wrapped)
  assert fileio.disk_full(e) and fileio.disk_full_path(e) is None
  e = _raised(lambda: open("/nonexistent/file"))
  assert not fileio.disk_full(e) and fileio.disk_full_path(e) is None


def test_a_small_write_the_disk_refuses_names_the_file_and_leaves_it_as_it_was(tmp_path, monkeypatch):
  path = str(tmp_path / "summary.json")
  fileio.atomic_write_json(path, {"step": 10})
  real_fsync = os.fsync

  def fsync_on_a_full_disk(fd):       # where delayed allocation reports a full disk
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  monkeypatch.setattr(os, "fsync", fsync_on_a_full_disk)
  e = _raised(lambda: fileio.atomic_write_json(path, {"step": 20}))
  assert isinstance(e, OSError) and e.errno == errno.ENOSPC and e.filename == path
  monkeypatch.setattr(os, "fsync", real_fsync)
  with open(path) as f:
    assert json.load(f) == {"step": 10}
  assert os.listdir(tmp_path) == ["summary.json"]
