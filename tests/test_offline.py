"""Evaluations of a finished run on its validation demos: the policy's offline action error (roboshape/eval/offline.py:
phases and windows) and whether its SAVi finds the cube, by the cube's size (roboshape/eval/slots.py)."""
import functools
import json
import os

import numpy as np
import pytest

from roboshape import rundir
from roboshape.encoders import savi as savi_encoder
from roboshape.eval import offline
from roboshape.eval import slots
from roboshape.models import savi
from roboshape.train import bc
from roboshape.train import pretrain


def test_phases_follow_the_experts_gripper_and_lift():
  actions = np.zeros((12, 7), np.float32)
  actions[:, -1] = 1.0
  actions[5:, -1] = -1.0          # closes at step 5
  actions[3, 2] = 0.5             # an upward move before the close is still the approach
  actions[8:, 2] = 0.4            # lifts from step 8
  got = offline.phases(actions)
  assert np.flatnonzero(got["approach"]).tolist() == [0, 1, 2, 3, 4]
  assert np.flatnonzero(got["grasp"]).tolist() == [5, 6, 7]
  assert np.flatnonzero(got["lift"]).tolist() == [8, 9, 10, 11]
  assert np.flatnonzero(got["first"]).tolist() == list(range(offline.FIRST_STEPS))
  push = offline.phases(np.ones((4, 7), np.float32))          # never closes: all approach
  assert push["approach"].all() and not push["grasp"].any() and not push["lift"].any()


def test_each_action_is_read_from_the_window_training_reads_it_in():
  # 6 actions, history 3: training's windows start at frames 0..3 (bc.Windows); the first frames are read in the
  # first window at their own position, the others at the last position of the window ending at them.
  start, position = offline.windows(6, 3)
  assert start.tolist() == [0, 0, 0, 1, 2, 3] and position.tolist() == [0, 1, 2, 2, 2, 2]
  data = dict(features=np.zeros((7, 1, 1), np.float32), action=np.zeros((7, 7), np.float32),
              offsets=np.array([0, 7]), success=np.array([True]))
  assert bc.Windows(data, 3, (np.ones(7), np.zeros(7))).window_start.tolist() == [0, 1, 2, 3]


@pytest.mark.usefixtures("cheap_xla")
def test_the_offline_figures_of_the_tiny_run(tiny_run):
  from roboshape.train import cache  # pylint: disable=import-outside-toplevel
  assert offline.main([tiny_run]) == 0
  with open(os.path.join(tiny_run, "eval", offline.OFFLINE_FILE)) as f:
    got = json.load(f)
  (features,) = [os.path.join(tiny_run, "features", k) for k in os.listdir(os.path.join(tiny_run, "features"))]
  val = cache.load_split(features, "val")
  lengths = np.diff(val["offsets"]) - 1                            # actions per episode
  assert got["episodes"] == int(val["success"].sum()) == 2
  phases = got["phases"]
  assert phases["approach"]["actions"] + phases["grasp"]["actions"] + phases["lift"]["actions"] == lengths.sum()
  assert phases["first"]["actions"] == np.minimum(lengths, offline.FIRST_STEPS).sum()
  assert all(np.isfinite(p["action_mse"]) for p in phases.values() if p["actions"])
  expert = np.mean([np.linalg.norm(val["action"][a:a + offline.FIRST_STEPS, :3], axis=-1).mean()
                    for a in val["offsets"][:-1]])
  assert got["first_move"]["expert"] == pytest.approx(expert, rel=1e-5)


@pytest.mark.usefixtures("cheap_xla")
def test_the_cube_by_its_size_adds_up_to_the_savis_validation_of_the_tiny_run(tiny_run):
  """slots.cube_by_area on the tiny run's validation frames (the synthetic red square is the cube, 4 of 256 pixels,
  in the 1-2% bin in every frame) against slots.evaluate, the validation the pretrain stage runs, on the same ones."""
  found = slots.cube_by_area(tiny_run)
  config = rundir.load_config(tiny_run)
  model, params, _ = savi_encoder.load(tiny_run)
  _, episodes = pretrain.data_source(config, tiny_run)
  metrics = slots.evaluate(functools.partial(savi.decompose, model), params, episodes, config.pretrain.eval.frames,
                           pool=model.input_pool)
  frames = sum(min(len(e["image"]), config.pretrain.eval.frames) for e in episodes)
  assert list(found) == ["front"]
  (row,) = [r for r in found["front"] if r["frames"]]
  assert (row["lo"], row["hi"], row["frames"]) == (0.01, 0.02, frames)
  assert row["iou"] == pytest.approx(metrics["cube_iou"]) and row["found"] == pytest.approx(metrics["cube_found"])
  assert slots.area_table(found).splitlines()[2] == (f"| front | 1.0% - 2.0% | {frames} | {row['iou']:.2f} | "
                                                     f"{row['found']:.0%} |")
