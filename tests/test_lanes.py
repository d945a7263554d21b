"""Grid runs in parallel lanes (roboshape/lanes.py): child processes pinned to disjoint cores, their exit codes and
one-line errors, and the grid's skip / fail rules applied to them."""
import json
import os

import pytest

from configs import common
from configs import reproduce
from roboshape import lanes
from roboshape import stages
from roboshape.errors import UserError


def test_lane_cores_deal_this_process_cores_once_each():
  cores = sorted(os.sched_getaffinity(0))
  for n in (1, 2, 99):
    dealt = lanes.lane_cores(n)
    assert len(dealt) == min(n, len(cores)) and all(dealt)
    assert sorted(c for lane in dealt for c in lane) == cores


def test_children_run_pinned_and_report_their_exit_codes(tmp_path):
  jobs = []
  for name in ("a", "bad"):
    config = common.get_config("push", "state", "tiny")
    config.stages = ()              # the child checks the config and the workdir, and saves config.json
    if name == "bad":
      config.eval.levels = ("L9",)
    jobs.append((name, config, str(tmp_path / name)))
  ended = {}
  lanes.run_parallel(jobs, 2, lambda job, code, line: ended.update({job[0]: (code, line)}), poll_seconds=0.2)
  assert ended["a"][0] == 0
  assert ended["bad"][0] == 2 and ended["bad"][1].startswith("roboshape: error: eval.levels")
  assert json.load(open(tmp_path / "a" / "config.json"))["encoder"] == "state"
  assert not (tmp_path / "bad" / "config.json").exists()          # bad input writes nothing but the log
  pinned = {}
  for name in ("a", "bad"):
    line = next(l for l in open(tmp_path / name / lanes.LOG_FILE) if " on cores " in l)
    pinned[name] = line.split(" on cores ")[1].split("]")[0]
  if len(os.sched_getaffinity(0)) >= 2:                            # they ran at once, each on its own core
    assert pinned["a"] != pinned["bad"] and "," not in pinned["a"] + pinned["bad"]


def test_a_grid_in_lanes_skips_a_failed_baseline_and_stops_for_savi(tmp_path):
  config = reproduce.get_config("tiny")
  config.grid.encoders, config.grid.lanes, config.stages = ("savi", "r3m"), 2, ("cache",)
  with pytest.raises(UserError, match=r"grid runs failed: push x savi \(.+\).*log\.txt"):
    stages.run(config, str(tmp_path / "grid"))    # no dataset: each run's cache stage fails with one line
  reason = json.load(open(tmp_path / "grid" / "push_r3m" / "SKIPPED.json"))["reason"]
  assert reason and "\n" not in reason and not reason.startswith("roboshape: error")
  assert not (tmp_path / "grid" / "push_savi" / "SKIPPED.json").exists()
