"""The RoboShape scene shared by the three tasks: Panda, table, red cube, distractors, backdrop, its cameras (the
front one, and the wrist one when asked for: roboshape/envs/camera.py).

Every reset rebuilds the scene (ManiSkill reconfiguration), so the number of distractors, their shapes, sizes and
colors, the background color and the table color all change per episode. Randomness comes only from the episode
seed: object identities from `np.random.default_rng([seed, 0])`, poses from `np.random.default_rng([seed, 1])`,
so one task + level + seed gives the same scene every time.

Subclasses (roboshape/envs/tasks.py) add the goal (`_build_goal`, `_sample_goal`) and `evaluate()`.
"""
import dataclasses
from typing import Dict, List, Optional, Tuple

import numpy as np
import sapien
import torch

from mani_skill.agents.robots import Panda
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.structs.actor import Actor
from mani_skill.utils.structs.pose import Pose
from transforms3d.euler import euler2quat

from roboshape.envs import camera
from roboshape.envs import ids
from roboshape.envs import palettes
from roboshape.envs import state as state_lib


CUBE_HALF_SIZE = 0.02
TABLE_HEIGHT = 0.92
ROBOT_BASE = (-0.615, 0.0, 0.0)
REST_QPOS = np.array([0.0, np.pi / 8, 0.0, -np.pi * 5 / 8, 0.0, np.pi * 3 / 4, np.pi / 4, 0.04, 0.04])
# Workspace on the table top (x forward from the robot, y to its left), meters.
CUBE_REGION = ((-0.08, 0.08), (-0.14, 0.14))
DISTRACTOR_REGION = ((-0.16, 0.16), (-0.22, 0.22))
CAMERA_EYE, CAMERA_TARGET, CAMERA_FOV = camera.EYE, camera.TARGET, camera.FOV   # roboshape/envs/camera.py


@dataclasses.dataclass
class SceneDraw:
  """What one episode's scene is made of (drawn at reconfiguration from the episode seed)."""
  background: Tuple[int, int, int]
  table: Tuple[int, int, int]
  shapes: List[str]
  sizes: List[float]
  colors: List[Tuple[int, int, int]]


def footprint(shape: str, size: float) -> float:
  """Radius of the disk that covers an object's footprint on the table (any yaw)."""
  return size * np.sqrt(2.0) if shape == "cube" else size


def yaw_quat(yaw: np.ndarray) -> np.ndarray:
  """Quaternions (wxyz) [..., 4] of rotations by `yaw` [...] about +z."""
  return np.stack([np.cos(yaw / 2), np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2)], -1)


def render_material(color, emissive: bool = False) -> sapien.render.RenderMaterial:
  rgba = palettes.rgba(color)
  if emissive:  # lit by nothing: renders as its own color, whatever the lights
    return sapien.render.RenderMaterial(emission=list(rgba), base_color=[0, 0, 0, 1], roughness=1.0)
  return sapien.render.RenderMaterial(base_color=list(rgba), roughness=0.7, specular=0.2)


class RoboShapeEnv(BaseEnv):
  """Panda on a table with the red cube, 1-4 random distractors and a colored backdrop; the front camera and any
  other of `cameras`.

  Args (besides BaseEnv's):
    level: generalization level, one of palettes.LEVEL_NAMES.
    resolution: side of every camera's square image, pixels.
    cameras: the cameras rendered (roboshape/envs/camera.py CAMERAS), the front one among them.
    min_distractors, max_distractors: number of distractors per episode, uniform in this range.
    robot_init_qpos_noise: half-width of the uniform noise added to the arm's rest joints, radians.
  """
  SUPPORTED_ROBOTS = ["panda"]
  agent: Panda
  # Subclasses set these.
  TASK = ""
  HORIZON = 100

  def __init__(self, *args, level: str = "train", resolution: int = 64, min_distractors: int = 1,
               max_distractors: int = 4, robot_uids: str = "panda", robot_init_qpos_noise: float = 0.08,
               cameras: Tuple[str, ...] = camera.DEFAULT, **kwargs):
    self.level = palettes.get_level(level)
    self.cameras = camera.check(cameras)
    if not 0 <= min_distractors <= max_distractors:
      raise ValueError(f"need 0 <= min_distractors <= max_distractors, got {min_distractors}, {max_distractors}")
    self.resolution = int(resolution)
    self.min_distractors = int(min_distractors)
    self.max_distractors = int(max_distractors)
    self.robot_init_qpos_noise = robot_init_qpos_noise
    self.draws: List[SceneDraw] = []
    self.distractors: List[List[Actor]] = []
    self.seg_lut = np.zeros(1, np.uint8)
    self.goal_pos: Optional[torch.Tensor] = None  # [N, 3] goal of each env (target / pick point / bin)
    kwargs.setdefault("reconfiguration_freq", 1)
    super().__init__(*args, robot_uids=robot_uids, **kwargs)

  # ---------------------------------------------------------------------------------------------- scene
  @property
  def _default_sensor_configs(self):
    configs = []
    for name in self.cameras:
      if name == camera.FRONT:
        pose = sapien_utils.look_at(eye=CAMERA_EYE, target=CAMERA_TARGET)
        configs.append(CameraConfig(name, pose, self.resolution, self.resolution, CAMERA_FOV, 0.01, 10.0))
      else:  # "wrist": on the hand, moving with it
        (xyz, rpy), offset = camera.WRIST_MOUNT, camera.WRIST_OFFSET
        pose = sapien.Pose(p=list(xyz), q=list(euler2quat(*rpy))) * sapien.Pose(p=list(offset))
        configs.append(CameraConfig(name, pose, self.resolution, self.resolution, camera.WRIST_FOV, 0.01, 10.0,
                                    mount=self.agent.robot.links_map[camera.WRIST_LINK]))
    return configs

  @property
  def _default_human_render_camera_configs(self):
    pose = sapien_utils.look_at(eye=CAMERA_EYE, target=CAMERA_TARGET)
    return CameraConfig("render_camera", pose, 256, 256, CAMERA_FOV, 0.01, 10.0)

  def _load_lighting(self, options: dict):
    """Ambient light, a light from above and one from the camera's side, so the faces the camera sees are lit."""
    self.scene.set_ambient_light([0.45, 0.45, 0.45])
    self.scene.add_directional_light([0, 0, -1], [0.5, 0.5, 0.5])
    self.scene.add_directional_light([-1, 0.3, -1], [0.6, 0.6, 0.6])

  def _load_agent(self, options: dict):
    super()._load_agent(options, sapien.Pose(p=list(ROBOT_BASE)))

  def _seeds(self) -> np.ndarray:
    return np.asarray(self._episode_seed, dtype=np.int64).reshape(-1)

  def _draw_scene(self, seed: int) -> SceneDraw:
    rng = np.random.default_rng([int(seed), 0])
    backgrounds = list(self.level.backgrounds.values())
    colors = list(self.level.distractor_colors.values())
    tables = list(palettes.TABLE_COLORS.values())
    n = int(rng.integers(self.min_distractors, self.max_distractors + 1))
    return SceneDraw(
        background=backgrounds[rng.integers(len(backgrounds))],
        table=tables[rng.integers(len(tables))],
        shapes=[palettes.SHAPES[rng.integers(len(palettes.SHAPES))] for _ in range(n)],
        sizes=[self.level.sample_size(rng) for _ in range(n)],
        colors=[colors[rng.integers(len(colors))] for _ in range(n)])

  def _load_scene(self, options: dict):
    seeds = self._seeds()
    self.draws = [self._draw_scene(seeds[i % len(seeds)]) for i in range(self.num_envs)]
    tables, backdrops, self.distractors = [], [], []
    for i, draw in enumerate(self.draws):
      tables.append(self._build_table(i, draw.table))
      backdrops.append(self._build_backdrop(i, draw.background))
      self.distractors.append([
          self._build_distractor(i, j, shape, size, color)
          for j, (shape, size, color) in enumerate(zip(draw.shapes, draw.sizes, draw.colors))])
    self.table = Actor.merge(tables, name="table")
    self.backdrop = Actor.merge(backdrops, name="backdrop")
    builder = self.scene.create_actor_builder()
    builder.add_box_collision(half_size=[CUBE_HALF_SIZE] * 3)
    builder.add_box_visual(half_size=[CUBE_HALF_SIZE] * 3, material=render_material(palettes.CUBE_COLOR))
    builder.initial_pose = sapien.Pose(p=[0, 0, CUBE_HALF_SIZE])
    self.cube = builder.build(name="cube")
    self.goal = self._build_goal()

  def _build_table(self, i: int, color) -> Actor:
    builder = self.scene.create_actor_builder()
    half = [0.6, 1.2, TABLE_HEIGHT / 2]
    builder.add_box_collision(half_size=half)
    builder.add_box_visual(half_size=half, material=render_material(color))
    builder.initial_pose = sapien.Pose(p=[-0.14, 0, -TABLE_HEIGHT / 2])
    builder.set_scene_idxs([i])
    return builder.build_kinematic(name=f"table_{i}")

  def _build_backdrop(self, i: int, color) -> Actor:
    """The floor under the table and a wall behind the robot, both in the background color."""
    builder = self.scene.create_actor_builder()
    builder.add_plane_collision(sapien.Pose(p=[0, 0, -TABLE_HEIGHT], q=[0.7071068, 0, -0.7071068, 0]))
    material = render_material(color, emissive=True)
    builder.add_box_visual(sapien.Pose(p=[0, 0, -TABLE_HEIGHT - 0.01]), half_size=[6, 6, 0.01], material=material)
    builder.add_box_visual(sapien.Pose(p=[-1.1, 0, 0.5]), half_size=[0.01, 6, 3], material=material)
    builder.initial_pose = sapien.Pose()
    builder.set_scene_idxs([i])
    return builder.build_static(name=f"backdrop_{i}")

  def _build_distractor(self, i: int, j: int, shape: str, size: float, color) -> Actor:
    builder = self.scene.create_actor_builder()
    material = render_material(color)
    if shape == "cube":
      builder.add_box_collision(half_size=[size] * 3)
      builder.add_box_visual(half_size=[size] * 3, material=material)
    elif shape == "sphere":
      builder.add_sphere_collision(radius=size)
      builder.add_sphere_visual(radius=size, material=material)
    elif shape == "cylinder":  # upright: the primitive's axis is x, turned to z
      upright = sapien.Pose(q=[0.7071068, 0, 0.7071068, 0])
      builder.add_cylinder_collision(upright, radius=size, half_length=size)
      builder.add_cylinder_visual(upright, radius=size, half_length=size, material=material)
    else:
      raise ValueError(f"unknown shape {shape!r}")
    builder.initial_pose = sapien.Pose(p=[0.5 + 0.2 * j, 2.0, size])
    builder.set_scene_idxs([i])
    return builder.build(name=f"distractor_{i}_{j}")

  def _build_goal(self) -> Optional[Actor]:
    """The task's visible goal (target region, bin), or None."""
    return None

  def _after_reconfigure(self, options):
    self.seg_lut = self._segmentation_lut()

  def _segmentation_lut(self) -> np.ndarray:
    """uint8 [max_id + 1]: ManiSkill's per-scene segmentation id -> RoboShape object id (roboshape/envs/ids.py)."""
    roles = {}
    for actor, role in ((self.table, ids.TABLE), (self.backdrop, ids.BACKDROP), (self.cube, ids.CUBE),
                        (self.goal, ids.GOAL)):
      if actor is not None:
        for obj in actor._objs:  # pylint: disable=protected-access
          roles[obj.per_scene_id] = role
    for actors in self.distractors:
      for j, actor in enumerate(actors):
        roles[actor._objs[0].per_scene_id] = ids.FIRST_DISTRACTOR + j  # pylint: disable=protected-access
    for link in self.agent.robot.links:
      for obj in link._objs:  # pylint: disable=protected-access
        roles[obj.entity.per_scene_id] = ids.HAND if link.name in ids.HAND_LINKS else ids.ROBOT
    lut = np.zeros(max(roles) + 1, np.uint8)
    for key, role in roles.items():
      lut[key] = role
    return lut

  # ---------------------------------------------------------------------------------------------- episode
  def _sample_goal(self, rng: np.random.Generator, cube_xy: np.ndarray) -> np.ndarray:
    """The goal position [3] for this episode (subclasses); may depend on the cube's position."""
    del rng, cube_xy
    return np.zeros(3)

  def _keep_out(self, cube_xy: np.ndarray, goal: np.ndarray) -> List[Tuple[np.ndarray, np.ndarray, float]]:
    """Segments (a, b, clearance) of the table the distractors must stay away from (subclasses add to it)."""
    return [(cube_xy, cube_xy, 0.06)]

  def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
    seeds = self._seeds()
    idx = env_idx.cpu().numpy()
    b = len(idx)
    qpos = np.zeros((b, len(REST_QPOS)))
    cube_p, cube_q, goal_p = np.zeros((b, 3)), np.zeros((b, 4)), np.zeros((b, 3))
    with torch.device(self.device):
      for k, i in enumerate(idx):
        rng = np.random.default_rng([int(seeds[i % len(seeds)]), 1])
        qpos[k] = REST_QPOS
        qpos[k, :7] += rng.uniform(-self.robot_init_qpos_noise, self.robot_init_qpos_noise, 7)
        cube_xy = np.array([rng.uniform(*CUBE_REGION[0]), rng.uniform(*CUBE_REGION[1])])
        cube_p[k] = [cube_xy[0], cube_xy[1], CUBE_HALF_SIZE]
        cube_q[k] = yaw_quat(rng.uniform(-np.pi / 4, np.pi / 4))
        goal_p[k] = self._sample_goal(rng, cube_xy)
        self._place_distractors(rng, i, cube_xy, goal_p[k])
      self.agent.reset(torch.as_tensor(qpos, dtype=torch.float32))
      self.agent.robot.set_pose(sapien.Pose(list(ROBOT_BASE)))
      self.cube.set_pose(Pose.create_from_pq(torch.as_tensor(cube_p, dtype=torch.float32),
                                             torch.as_tensor(cube_q, dtype=torch.float32)))
      if self.goal_pos is None:
        self.goal_pos = torch.zeros((self.num_envs, 3), dtype=torch.float32)
      self.goal_pos[torch.as_tensor(idx)] = torch.as_tensor(goal_p, dtype=torch.float32)
      if self.goal is not None:
        self.goal.set_pose(Pose.create_from_pq(torch.as_tensor(goal_p, dtype=torch.float32)))

  def _place_distractors(self, rng: np.random.Generator, i: int, cube_xy: np.ndarray, goal: np.ndarray):
    """Rejection-samples non-overlapping distractor positions away from the task's keep-out segments."""
    draw = self.draws[i]
    keep_out = self._keep_out(cube_xy, goal)
    placed: List[Tuple[np.ndarray, float]] = []
    for j, actor in enumerate(self.distractors[i]):
      radius = footprint(draw.shapes[j], draw.sizes[j])
      xy = None
      for attempt in range(200):
        cand = np.array([rng.uniform(*DISTRACTOR_REGION[0]), rng.uniform(*DISTRACTOR_REGION[1])])
        if any(np.linalg.norm(cand - p) < radius + r + 0.015 for p, r in placed):
          continue
        if attempt < 150 and any(segment_distance(cand, a, b) < radius + c for a, b, c in keep_out):
          continue
        xy = cand
        break
      if xy is None:  # crowded table: park it at the table's side, out of the workspace
        xy = np.array([0.3, (0.35 + 0.1 * j) * (1 if j % 2 else -1)])
      placed.append((xy, radius))
      yaw = rng.uniform(-np.pi, np.pi) if draw.shapes[j] == "cube" else 0.0
      pose = Pose.create_from_pq(torch.tensor([[xy[0], xy[1], draw.sizes[j]]], dtype=torch.float32),
                                 torch.as_tensor(yaw_quat(np.array([yaw])), dtype=torch.float32))
      actor.set_pose(pose)

  # ---------------------------------------------------------------------------------------------- state
  def privileged_state(self) -> Dict[str, torch.Tensor]:
    """What the oracle expert reads: tcp_p [N, 3], tcp_q [N, 4] (wxyz), cube_p [N, 3], cube_q [N, 4],
    goal_p [N, 3], gripper [N] (finger opening, meters), grasped bool [N], obstacles [N, K, 4] (the distractors'
    x, y, footprint radius and height; K = the most distractors of any env, unused rows far away)."""
    tcp = self.agent.tcp.pose
    cube = self.cube.pose
    k = max(1, max(len(d) for d in self.distractors))
    obstacles = torch.tensor([[10.0, 10.0, 0.0, 0.0]]).repeat(self.num_envs, k, 1)
    for i, (draw, actors) in enumerate(zip(self.draws, self.distractors)):
      for j, actor in enumerate(actors):
        p = actor.pose.p[0].cpu()
        obstacles[i, j] = torch.tensor([p[0], p[1], footprint(draw.shapes[j], draw.sizes[j]), p[2] + draw.sizes[j]])
    return dict(tcp_p=tcp.p, tcp_q=tcp.q, cube_p=cube.p, cube_q=cube.q, goal_p=self.goal_pos.to(tcp.p.device),
                gripper=self.agent.robot.get_qpos()[:, -2:].sum(-1), grasped=self.agent.is_grasping(self.cube),
                obstacles=obstacles.to(tcp.p.device))

  def state_vector(self) -> np.ndarray:
    """The privileged state float32 [N, envs.state.DIM] (layout in roboshape/envs/state.py): what the experts read,
    plus the arm's joints and each distractor's position and size."""
    s = self.privileged_state()
    k = max(1, max(len(d) for d in self.distractors))
    rows = np.zeros((self.num_envs, k, 4), np.float32)
    present = np.zeros((self.num_envs, k), bool)
    for i, (draw, actors) in enumerate(zip(self.draws, self.distractors)):
      for j, (actor, size) in enumerate(zip(actors, draw.sizes)):
        rows[i, j] = list(actor.pose.p[0].cpu().numpy()) + [size]
        present[i, j] = True
    return state_lib.pack(s["tcp_p"].cpu().numpy(), s["tcp_q"].cpu().numpy(), s["gripper"].cpu().numpy(),
                          self.agent.robot.get_qpos()[:, :7].cpu().numpy(), s["cube_p"].cpu().numpy(),
                          s["cube_q"].cpu().numpy(), s["goal_p"].cpu().numpy(), rows, present)

  def frames(self, obs, name: str = camera.FRONT) -> Tuple[np.ndarray, np.ndarray]:
    """Camera `name`'s rgb uint8 [N, H, W, 3] and RoboShape segmentation uint8 [N, H, W] from an observation."""
    data = obs["sensor_data"][name]
    rgb = data["rgb"].cpu().numpy().astype(np.uint8)
    seg = np.zeros(rgb.shape[:3], np.uint8)
    if "segmentation" in data:
      ids = data["segmentation"][..., 0].cpu().numpy().astype(np.int64)
      ids = np.where((ids >= 0) & (ids < len(self.seg_lut)), ids, 0)
      seg = self.seg_lut[ids]
    return rgb, seg

  @staticmethod
  def depth(obs, name: str = camera.FRONT) -> np.ndarray:
    """Camera `name`'s depth uint16 [N, H, W] in millimetres (an env made with obs_mode "rgb+depth+...")."""
    depth = obs["sensor_data"][name]["depth"][..., 0].cpu().numpy().astype(np.int64)
    return np.clip(depth, 0, np.iinfo(np.uint16).max).astype(np.uint16)

  def _get_obs_extra(self, info: dict):
    return dict(tcp_pose=self.agent.tcp.pose.raw_pose, goal_pos=self.goal_pos,
                cube_pose=self.cube.pose.raw_pose)

  def compute_dense_reward(self, obs, action, info):
    """A sparse reward: 1 on success steps (stored in the demos; the policy is trained by imitation)."""
    del obs, action
    return info["success"].float()

  def compute_normalized_dense_reward(self, obs, action, info):
    return self.compute_dense_reward(obs, action, info)


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
  """Distance from point p [2] to the segment [a, b] (2-D)."""
  ab = b - a
  denom = float(ab @ ab)
  t = 0.0 if denom < 1e-12 else float(np.clip((p - a) @ ab / denom, 0.0, 1.0))
  return float(np.linalg.norm(p - (a + t * ab)))

