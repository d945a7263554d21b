"""The three RoboShape tasks, registered with ManiSkill on import: push, pick and place.

Success is read from the simulator state in `evaluate()`, with the thresholds written below in each class.
Horizons (`HORIZON`, control steps at 20 Hz) are at least 1.5x the expert's 95th-percentile episode length
(measured by benchmarks/expert_success.py).

Milestones (their names: roboshape.envs.MILESTONES). Each task's `milestones(start, info)` says which hold at the
current step, given the cube's position at reset and the step's `evaluate()` info (nothing is computed twice);
closed-loop evaluation records which ones a rollout ever reached.
"""
from typing import List, Tuple

import numpy as np
import sapien
import torch

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.actor import Actor

from roboshape.envs.milestones import MILESTONES as TASK_MILESTONES
from roboshape.envs import palettes
from roboshape.envs import scene

ENV_IDS = {"push": "RoboShape-Push-v1", "pick": "RoboShape-Pick-v1", "place": "RoboShape-Place-v1"}


MOVED = 0.02    # the cube moved this far (m, in the table plane) from where it was at reset
LIFTED = 0.03   # the grasped cube's centre this far (m) above its height at reset


def _lifted(env, start: torch.Tensor, info: dict) -> Tuple[torch.Tensor, torch.Tensor]:
  """(grasped, grasped and lifted) bool [N], from the step's info["is_grasped"]."""
  grasped = info["is_grasped"]
  return grasped, grasped & (env.cube.pose.p[:, 2] - start[:, 2] >= LIFTED)


def _sample_point_at(rng: np.random.Generator, origin: np.ndarray, dist_range, region) -> np.ndarray:
  """A point of `region` ((x0, x1), (y0, y1)) at a distance in `dist_range` from `origin` [2]."""
  for _ in range(1000):
    angle = rng.uniform(-np.pi, np.pi)
    xy = origin + rng.uniform(*dist_range) * np.array([np.cos(angle), np.sin(angle)])
    if region[0][0] <= xy[0] <= region[0][1] and region[1][0] <= xy[1] <= region[1][1]:
      return xy
  raise RuntimeError("no goal position found; the goal region is too small for the distance range")


@register_env(ENV_IDS["push"], max_episode_steps=90)
class PushEnv(scene.RoboShapeEnv):
  """Push the red cube onto the green target region drawn on the table.

  Success: the cube's center lies within SUCCESS_DIST of the target's center (in the table plane).
  """
  TASK = "push"
  HORIZON = 90
  TARGET_RADIUS = 0.06          # drawn disk
  SUCCESS_DIST = TARGET_RADIUS  # cube center on the drawn disk (xy): success is what the picture shows
  GOAL_DIST = (0.1, 0.18)       # cube to target at reset
  GOAL_REGION = ((-0.14, 0.14), (-0.2, 0.2))

  def _build_goal(self) -> Actor:
    builder = self.scene.create_actor_builder()
    builder.add_cylinder_visual(sapien.Pose(q=[0.7071068, 0, 0.7071068, 0]), radius=self.TARGET_RADIUS,
                                half_length=0.0005, material=scene.render_material(palettes.GOAL_COLOR))
    builder.initial_pose = sapien.Pose(p=[0, 0, 0.001])
    return builder.build_kinematic(name="target")

  def _sample_goal(self, rng, cube_xy):
    xy = _sample_point_at(rng, cube_xy, self.GOAL_DIST, self.GOAL_REGION)
    return np.array([xy[0], xy[1], 0.001])

  def _keep_out(self, cube_xy, goal) -> List[Tuple[np.ndarray, np.ndarray, float]]:
    direction = (goal[:2] - cube_xy) / max(np.linalg.norm(goal[:2] - cube_xy), 1e-6)
    return [(cube_xy - 0.09 * direction, goal[:2], 0.06)]

  def evaluate(self):
    dist = torch.linalg.norm(self.cube.pose.p[:, :2] - self.goal_pos[:, :2].to(self.device), dim=1)
    return {"success": dist <= self.SUCCESS_DIST, "cube_to_goal": dist}

  MILESTONES = TASK_MILESTONES["push"]

  def milestones(self, start: torch.Tensor, info: dict) -> torch.Tensor:
    """bool [N, 3]: the cube moved MOVED from `start` [N, 3]; it covered half its reset distance to the target's
    edge (so on the target implies halfway); it is on the target (success)."""
    goal = self.goal_pos[:, :2].to(self.device)
    start_dist = torch.linalg.norm(start[:, :2] - goal, dim=1)
    moved = torch.linalg.norm(self.cube.pose.p[:, :2] - start[:, :2], dim=1) >= MOVED
    halfway = info["cube_to_goal"] <= self.SUCCESS_DIST + 0.5 * (start_dist - self.SUCCESS_DIST)
    return torch.stack([moved, halfway, info["success"]], dim=1)


@register_env(ENV_IDS["pick"], max_episode_steps=90)
class PickEnv(scene.RoboShapeEnv):
  """Grasp the red cube and hold it at a fixed point above the table (the point is not shown).

  Success: the cube is grasped and its center lies within SUCCESS_DIST of GOAL.
  """
  TASK = "pick"
  HORIZON = 90
  GOAL = (0.02, 0.0, 0.16)
  SUCCESS_DIST = 0.03

  def _sample_goal(self, rng, cube_xy):
    del rng, cube_xy
    return np.array(self.GOAL)

  def _keep_out(self, cube_xy, goal):
    return [(cube_xy, cube_xy, 0.07)]

  def evaluate(self):
    dist = torch.linalg.norm(self.cube.pose.p - self.goal_pos.to(self.device), dim=1)
    grasped = self.agent.is_grasping(self.cube)
    return {"success": (dist <= self.SUCCESS_DIST) & grasped, "cube_to_goal": dist, "is_grasped": grasped}

  MILESTONES = TASK_MILESTONES["pick"]

  def milestones(self, start: torch.Tensor, info: dict) -> torch.Tensor:
    """bool [N, 3]: the cube is grasped; grasped and LIFTED above its reset height; held at the point (success)."""
    grasped, lifted = _lifted(self, start, info)
    return torch.stack([grasped, lifted, info["success"]], dim=1)


@register_env(ENV_IDS["place"], max_episode_steps=120)
class PlaceEnv(scene.RoboShapeEnv):
  """Pick the red cube and release it inside the green bin.

  Success: the cube's center is inside the bin's inner square, it rests on the bin floor (center below
  REST_HEIGHT) and the gripper no longer holds it.
  """
  TASK = "place"
  HORIZON = 120
  INNER_HALF = 0.045            # inner half side of the bin
  WALL = 0.006                  # wall thickness
  WALL_TOP = 0.05               # height of the rim above the table
  FLOOR_TOP = 0.008             # height of the bin floor above the table
  REST_HEIGHT = FLOOR_TOP + scene.CUBE_HALF_SIZE + 0.01
  GOAL_DIST = (0.15, 0.25)
  GOAL_REGION = ((-0.12, 0.13), (-0.22, 0.22))

  def _build_goal(self) -> Actor:
    builder = self.scene.create_actor_builder()
    material = scene.render_material(palettes.GOAL_COLOR)
    outer = self.INNER_HALF + self.WALL
    parts = [((0, 0, self.FLOOR_TOP / 2), (outer, outer, self.FLOOR_TOP / 2))]
    wall_h = self.WALL_TOP / 2
    for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
      center = (sx * (outer - self.WALL / 2), sy * (outer - self.WALL / 2), wall_h)
      half = (self.WALL / 2, outer, wall_h) if sx else (outer, self.WALL / 2, wall_h)
      parts.append((center, half))
    for center, half in parts:
      builder.add_box_collision(sapien.Pose(p=list(center)), half_size=list(half))
      builder.add_box_visual(sapien.Pose(p=list(center)), half_size=list(half), material=material)
    builder.initial_pose = sapien.Pose(p=[0.1, 0, 0])
    return builder.build_kinematic(name="bin")

  def _sample_goal(self, rng, cube_xy):
    xy = _sample_point_at(rng, cube_xy, self.GOAL_DIST, self.GOAL_REGION)
    return np.array([xy[0], xy[1], 0.0])

  def _keep_out(self, cube_xy, goal):
    outer = (self.INNER_HALF + self.WALL) * np.sqrt(2.0)
    return [(cube_xy, cube_xy, 0.07), (goal[:2], goal[:2], outer + 0.03)]

  def evaluate(self):
    offset = self.cube.pose.p - self.goal_pos.to(self.device)
    inside = torch.all(torch.abs(offset[:, :2]) <= self.INNER_HALF - 0.005, dim=1)
    resting = offset[:, 2] <= self.REST_HEIGHT
    grasped = self.agent.is_grasping(self.cube)
    return {"success": inside & resting & ~grasped, "inside": inside, "is_grasped": grasped}

  MILESTONES = TASK_MILESTONES["place"]

  def milestones(self, start: torch.Tensor, info: dict) -> torch.Tensor:
    """bool [N, 4]: the cube is grasped; grasped and LIFTED above its reset height; its centre is over the bin's
    inner square (at any height); it rests in the bin, released (success)."""
    grasped, lifted = _lifted(self, start, info)
    return torch.stack([grasped, lifted, info["inside"], info["success"]], dim=1)


TASK_CLASSES = {"push": PushEnv, "pick": PickEnv, "place": PlaceEnv}
