"""Oracle experts: closed-loop waypoint controllers on privileged state, batched over ManiSkill's num_envs.

Each expert reads `env.unwrapped.privileged_state()` (torch tensors [N, ...]) and returns pd_ee_delta_pose
actions float32 [N, 7] in [-1, 1]: a position step (x 0.1 m), a rotation step (x 0.1 rad, XYZ Euler) and the
gripper (1 open, -1 closed). A per-env phase machine walks the waypoints (approach, descend, grasp, lift, carry,
release, retreat) and falls back to the approach when a grasp or a push is lost, so the same code serves one CPU env
or thousands of GPU envs. No motion planner is used.
"""
from typing import Dict

import numpy as np
import torch

from mani_skill.utils.geometry import rotation_conversions as rc

POS_SCALE = 0.1   # meters per unit of position action
# Radians per unit of rotation action. Signed: the installed controller scales rotation actions by its lower
# bound (-0.1), so a positive action turns the gripper the negative way.
ROT_SCALE = -0.1
OPEN, CLOSED = 1.0, -1.0
CUBE_HALF = 0.02
_DOWN = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # gripper pointing down, yaw 0


def _yaw(rot: torch.Tensor) -> torch.Tensor:
  """Yaw [N] of rotation matrices [N, 3, 3] (heading of their x axis in the table plane)."""
  return torch.atan2(rot[:, 1, 0], rot[:, 0, 0])


def _wrap(angle: torch.Tensor, period: float) -> torch.Tensor:
  """Angle wrapped into [-period / 2, period / 2)."""
  return torch.remainder(angle + period / 2, period) - period / 2


def _rot_z(yaw: torch.Tensor) -> torch.Tensor:
  c, s, z, o = torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw), torch.ones_like(yaw)
  return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


def servo(tcp_p, tcp_q, target_p, target_yaw, gripper, max_step: float = 0.6) -> torch.Tensor:
  """The action [N, 7] moving the tcp toward target_p [N, 3] with the gripper down at target_yaw [N]."""
  step = (target_p - tcp_p) / POS_SCALE
  norm = torch.linalg.norm(step, dim=1, keepdim=True).clamp(min=1e-9)
  step = step * torch.clamp(max_step / norm, max=1.0)
  rot = rc.quaternion_to_matrix(tcp_q)
  want = _rot_z(target_yaw) @ _DOWN.to(tcp_p)
  delta = rc.matrix_to_euler_angles(want @ rot.transpose(1, 2), "XYZ") / ROT_SCALE
  rnorm = torch.linalg.norm(delta, dim=1, keepdim=True).clamp(min=1e-9)
  delta = delta * torch.clamp(1.0 / rnorm, max=1.0)
  grip = torch.as_tensor(gripper, dtype=tcp_p.dtype, device=tcp_p.device).expand(tcp_p.shape[0])
  return torch.cat([step, delta, grip[:, None]], 1).clamp(-1, 1).float()


# The gripper seen from above as rectangles around the tcp: (half length along the fingers' closing axis, half
# width across it, lowest top height of an obstacle that touches it). Fingers, then the hand above them.
OPEN_ZONES = ((0.06, 0.016, 0.0), (0.115, 0.04, 0.055))
CLOSED_ZONES = ((0.02, 0.016, 0.0), (0.115, 0.04, 0.055))


def clearance(obstacles: torch.Tensor, center: torch.Tensor, yaw: torch.Tensor, zones) -> torch.Tensor:
  """Smallest gap [N] between obstacles [N, K, 4] (x, y, radius, top) and the gripper's zones at center [N, 2]
  with yaw [N] (heading of the tcp's x axis; the fingers close along its y axis)."""
  rel = obstacles[:, :, :2] - center[:, None]
  close = torch.stack([-torch.sin(yaw), torch.cos(yaw)], -1)[:, None]
  across = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)[:, None]
  u, w = torch.abs((rel * close).sum(-1)), torch.abs((rel * across).sum(-1))
  gaps = []
  for half_u, half_w, min_top in zones:
    gap = torch.hypot(torch.relu(u - half_u), torch.relu(w - half_w)) - obstacles[:, :, 2]
    gap = torch.where(obstacles[:, :, 3] >= min_top, gap, torch.ones_like(gap))
    gaps.append(gap.min(1).values)
  return torch.minimum(*gaps)


class Expert:
  """Base class: per-env phases and step counters; subclasses implement `_act`."""

  def __init__(self, num_envs: int, device="cpu"):
    self.phase = torch.zeros(num_envs, dtype=torch.long, device=device)
    self.count = torch.zeros(num_envs, dtype=torch.long, device=device)

  def reset(self, mask: torch.Tensor = None) -> None:
    """Restarts the phase machine of the envs in `mask` bool [N] (all when None)."""
    if mask is None:
      mask = torch.ones_like(self.phase, dtype=torch.bool)
    self.phase[mask] = 0
    self.count[mask] = 0

  def act(self, state: Dict[str, torch.Tensor]) -> torch.Tensor:
    """Actions float32 [N, 7] for the privileged state (see RoboShapeEnv.privileged_state)."""
    state = {k: v.to(self.phase.device) for k, v in state.items()}
    action = self._act(state)
    self.count += 1
    return action

  def _goto(self, mask, phase):
    """Moves the envs in `mask` to `phase`, restarting their step counters."""
    changed = mask & (self.phase != phase)
    self.phase[changed] = phase
    self.count[changed] = 0

  def _act(self, s):
    raise NotImplementedError


class GraspExpert(Expert):
  """Shared approach / descend / grasp / lift for pick and place; subclasses carry the cube."""
  APPROACH, DESCEND, CLOSE, CARRY = 0, 1, 2, 3

  def __init__(self, num_envs: int, device="cpu"):
    super().__init__(num_envs, device)
    self.turn = torch.zeros(num_envs, dtype=torch.bool, device=device)

  def _grasp_yaw(self, s):
    """The gripper yaw [N] to grasp the cube with (the cube face pair whose side has more room), and the current."""
    grip_yaw = _yaw(rc.quaternion_to_matrix(s["tcp_q"]))
    cube_yaw = _yaw(rc.quaternion_to_matrix(s["cube_q"]))
    choosing = self.phase == self.APPROACH
    if choosing.any():
      center = s["cube_p"][:, :2]
      turn = (clearance(s["obstacles"], center, cube_yaw + np.pi / 2, OPEN_ZONES)
              > clearance(s["obstacles"], center, cube_yaw, OPEN_ZONES) + 0.005)
      self.turn = torch.where(choosing, turn, self.turn)
    want = cube_yaw + self.turn.float() * (np.pi / 2)
    return grip_yaw + _wrap(want - grip_yaw, np.pi), grip_yaw

  def _grasp_phases(self, s):
    """Targets for phases APPROACH..CLOSE; returns (target_p, yaw, gripper) and updates phases."""
    tcp, cube = s["tcp_p"], s["cube_p"]
    yaw, grip_yaw = self._grasp_yaw(s)
    yaw_err = torch.abs(_wrap(yaw - grip_yaw, 2 * np.pi))
    above = cube + torch.tensor([0.0, 0.0, 0.08]).to(cube)
    grasp_at = cube.clone()
    grasp_at[:, 2] = torch.clamp(cube[:, 2] - 0.004, min=0.014)
    xy_err = torch.linalg.norm(tcp[:, :2] - cube[:, :2], dim=1)

    p = self.phase
    self._goto((p == self.APPROACH) & (xy_err < 0.008) & (torch.abs(tcp[:, 2] - above[:, 2]) < 0.03)
               & (yaw_err < 0.08), self.DESCEND)
    p = self.phase
    self._goto((p == self.DESCEND) & (xy_err > 0.02), self.APPROACH)
    self._goto((p == self.DESCEND) & (torch.linalg.norm(tcp - grasp_at, dim=1) < 0.008), self.CLOSE)
    p = self.phase
    self._goto((p == self.CLOSE) & (self.count >= 5), self.CARRY)
    # A lost grasp (fingers shut on nothing, or the cube back on the table) starts over.
    p = self.phase
    lost = (p >= self.CARRY) & (self.count >= 3) & ((s["gripper"] < 0.004) | (
        ~s["grasped"] & (torch.linalg.norm(tcp - cube, dim=1) > 0.03)))
    lost &= self._grasp_matters()
    self._goto(lost, self.APPROACH)

    p = self.phase
    target = torch.where((p == self.APPROACH)[:, None], above, grasp_at)
    gripper = torch.where(p >= self.CLOSE, CLOSED, OPEN)
    return target, yaw, gripper

  def _grasp_matters(self):
    return torch.ones_like(self.phase, dtype=torch.bool)


class PickExpert(GraspExpert):
  """Grasps the cube and brings it to the task's fixed goal, then holds it there."""

  def _act(self, s):
    target, yaw, gripper = self._grasp_phases(s)
    carry = self.phase == self.CARRY
    # Aim the cube (not the tcp) at the goal; first lift straight up.
    offset = s["tcp_p"] - s["cube_p"]
    carry_target = s["goal_p"] + offset
    low = s["cube_p"][:, 2] < 0.06
    lift = s["tcp_p"].clone()
    lift[:, 2] = s["goal_p"][:, 2]
    carry_target = torch.where(low[:, None], lift, carry_target)
    target = torch.where(carry[:, None], carry_target, target)
    max_step = torch.where(carry, 0.4, 0.6)
    return _servo_rows(s, target, yaw, gripper, max_step)


class PlaceExpert(GraspExpert):
  """Grasps the cube, carries it high over the bin, lowers it below the rim, opens, then retreats up."""
  OVER, LOWER, RELEASE, RETREAT = 4, 5, 6, 7
  CARRY_HEIGHT = 0.16
  RELEASE_HEIGHT = 0.065   # cube center above the table at release (bin rim at 0.05)

  def _grasp_matters(self):
    return self.phase <= self.LOWER

  def _act(self, s):
    target, yaw, gripper = self._grasp_phases(s)
    tcp, cube, goal = s["tcp_p"], s["cube_p"], s["goal_p"]
    offset = tcp - cube
    high_over = goal.clone()
    high_over[:, 2] = self.CARRY_HEIGHT
    lift = tcp.clone()
    lift[:, 2] = self.CARRY_HEIGHT + offset[:, 2]
    xy_err = torch.linalg.norm(cube[:, :2] - goal[:, :2], dim=1)
    p = self.phase
    self._goto((p == self.CARRY) & (cube[:, 2] > self.CARRY_HEIGHT - 0.04), self.OVER)
    self._goto((p == self.OVER) & (xy_err < 0.012), self.LOWER)
    low_over = goal.clone()
    low_over[:, 2] = self.RELEASE_HEIGHT
    self._goto((p == self.LOWER) & (torch.abs(cube[:, 2] - self.RELEASE_HEIGHT) < 0.01) & (xy_err < 0.015),
               self.RELEASE)
    self._goto((self.phase == self.RELEASE) & (self.count >= 4), self.RETREAT)
    p = self.phase
    retreat = tcp.clone()
    retreat[:, 2] = 0.2
    for phase, where in ((self.CARRY, lift), (self.OVER, high_over + offset), (self.LOWER, low_over + offset),
                         (self.RELEASE, tcp), (self.RETREAT, retreat)):
      target = torch.where((p == phase)[:, None], where, target)
    gripper = torch.where(p >= self.RELEASE, OPEN, gripper)
    max_step = torch.where(p == self.LOWER, 0.25, torch.where(p >= self.CARRY, 0.4, 0.6))
    return _servo_rows(s, target, yaw, gripper, max_step)


class PushExpert(Expert):
  """Closes the gripper, goes behind the cube (seen from the target), descends and pushes it onto the target."""
  ABOVE, DESCEND, PUSH = 0, 1, 2
  PUSH_HEIGHT = 0.018
  BEHIND = CUBE_HALF + 0.03

  def __init__(self, num_envs: int, device="cpu"):
    super().__init__(num_envs, device)
    self.turn = torch.zeros(num_envs, dtype=torch.bool, device=device)

  def _act(self, s):
    tcp, cube, goal = s["tcp_p"], s["cube_p"], s["goal_p"]
    to_goal = goal[:, :2] - cube[:, :2]
    dist = torch.linalg.norm(to_goal, dim=1, keepdim=True).clamp(min=1e-6)
    d = to_goal / dist
    normal = torch.stack([-d[:, 1], d[:, 0]], 1)
    rel = tcp[:, :2] - cube[:, :2]
    along, lateral = (rel * d).sum(1), (rel * normal).sum(1)
    pre = cube[:, :2] - d * self.BEHIND
    z = torch.full_like(dist[:, 0], self.PUSH_HEIGHT)
    pre_low = torch.cat([pre, z[:, None]], 1)
    pre_high = torch.cat([pre, (z + 0.07)[:, None]], 1)
    push = torch.cat([cube[:, :2] - d * (CUBE_HALF + 0.012) + d * torch.clamp(dist, max=0.03), z[:, None]], 1)

    p = self.phase
    self._goto((p == self.ABOVE) & (torch.linalg.norm(tcp[:, :2] - pre, dim=1) < 0.01), self.DESCEND)
    p = self.phase
    self._goto((p == self.DESCEND) & (torch.linalg.norm(tcp[:, :2] - pre, dim=1) > 0.02), self.ABOVE)
    self._goto((p == self.DESCEND) & (torch.abs(tcp[:, 2] - self.PUSH_HEIGHT) < 0.01), self.PUSH)
    p = self.phase
    off_line = (torch.abs(lateral) > 0.012) | (along > -CUBE_HALF + 0.002)
    self._goto((p == self.PUSH) & off_line & (self.count > 1), self.ABOVE)

    p = self.phase
    target = torch.where((p == self.ABOVE)[:, None], pre_high, torch.where((p == self.DESCEND)[:, None], pre_low, push))
    # Fingers closing across the push (a wide pusher), unless the hand then hits a tall distractor beside the path.
    across = torch.atan2(d[:, 1], d[:, 0])
    if (p == self.ABOVE).any():
      turn = clearance(s["obstacles"], pre, across + np.pi / 2, CLOSED_ZONES) > \
          clearance(s["obstacles"], pre, across, CLOSED_ZONES) + 0.005
      self.turn = torch.where(p == self.ABOVE, turn, self.turn)
    grip_yaw = _yaw(rc.quaternion_to_matrix(s["tcp_q"]))
    yaw = grip_yaw + _wrap(across + self.turn.float() * (np.pi / 2) - grip_yaw, np.pi)
    max_step = torch.where(p == self.PUSH, 0.25, 0.6)
    return _servo_rows(s, target, yaw, torch.full_like(yaw, CLOSED), max_step)


def _servo_rows(s, target, yaw, gripper, max_step) -> torch.Tensor:
  """`servo` with a per-env gripper [N] and max_step [N]."""
  action = servo(s["tcp_p"], s["tcp_q"], target, yaw, 0.0, max_step=1.0)
  step = action[:, :3]
  norm = torch.linalg.norm(step, dim=1, keepdim=True).clamp(min=1e-9)
  action[:, :3] = step * torch.clamp(max_step[:, None] / norm, max=1.0)
  action[:, 6] = torch.as_tensor(gripper, dtype=action.dtype)
  return action


EXPERTS = {"push": PushExpert, "pick": PickExpert, "place": PlaceExpert}


def make_expert(task: str, num_envs: int, device="cpu") -> Expert:
  """The oracle expert of `task` for `num_envs` parallel envs."""
  return EXPERTS[task](num_envs, device)
