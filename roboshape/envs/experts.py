"""Oracle experts: closed-loop waypoint controllers on privileged state, batched over ManiSkill's num_envs.

Each expert reads `env.unwrapped.privileged_state()` (torch tensors [N, ...]) and returns pd_ee_delta_pose
actions float32 [N, 7] in [-1, 1]: a position step (x 0.1 m), a rotation step (x 0.1 rad, XYZ Euler) and the
gripper (1 open, -1 closed). Each expert reads its phase (approach, descend, grasp, lift, carry, release, retreat)
off the current state at every step and keeps no memory between steps, so its action is a function of what the
state shows (a policy can infer it) and it falls back to the approach when a grasp or a push is lost. The same code
serves one CPU env or thousands of GPU envs. No motion planner is used.
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


def servo(tcp_p, tcp_q, target_p, target_yaw, gripper, max_step: float = 0.6, rot_gain: float = 1.0) -> torch.Tensor:
  """The action [N, 7] moving the tcp toward target_p [N, 3] with the gripper down at target_yaw [N].

  The rotation action is rot_gain x the orientation error (in units of the controller's 0.1 rad), its norm capped at
  1: rot_gain 1 saturates beyond 0.1 rad of error; a smaller gain turns proportionally over a wider range."""
  step = (target_p - tcp_p) / POS_SCALE
  norm = torch.linalg.norm(step, dim=1, keepdim=True).clamp(min=1e-9)
  step = step * torch.clamp(max_step / norm, max=1.0)
  rot = rc.quaternion_to_matrix(tcp_q)
  want = _rot_z(target_yaw) @ _DOWN.to(tcp_p)
  delta = rot_gain * rc.matrix_to_euler_angles(want @ rot.transpose(1, 2), "XYZ") / ROT_SCALE
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
  """Base class of the memoryless experts: `act(state)` is a function of the current privileged state alone.

  No phase machine, counter or latched choice survives from one step to the next, so the same state always gets
  the same action whatever came before it: a policy that observes the state (or enough of its history) can infer
  every action it is trained to imitate. `phase` holds the phase of each env at the last call, for inspection
  only; nothing reads it back.
  """

  def __init__(self, num_envs: int, device="cpu"):
    self.phase = torch.zeros(num_envs, dtype=torch.long, device=device)

  def reset(self, mask: torch.Tensor = None) -> None:
    """Kept for callers that reset an expert with its env: there is no memory to clear."""
    del mask

  def act(self, state: Dict[str, torch.Tensor]) -> torch.Tensor:
    """Actions float32 [N, 7] for the privileged state (see RoboShapeEnv.privileged_state)."""
    state = {k: v.to(self.phase.device) for k, v in state.items()}
    action, self.phase = self._act(state)
    return action

  def _act(self, s):
    """(actions [N, 7], phase [N]) for the state `s`."""
    raise NotImplementedError


def _pick_yaw(s, center, base_yaw, zones, choosing, prefer_current: bool = False):
  """The gripper yaw [N] to use: base_yaw or base_yaw + pi/2 (both mod pi).

  Where `choosing`, the one whose gripper zones at `center` have more clearance (by 5 mm); with `prefer_current`,
  the one nearer the gripper's current yaw unless its clearance is under 1 cm and the other's is 5 mm more.
  Elsewhere the one nearer the gripper's current yaw, so a choice made while approaching is kept without being
  remembered. Returns (yaw unwrapped next to the current yaw [N], current yaw [N]).
  """
  grip_yaw = _yaw(rc.quaternion_to_matrix(s["tcp_q"]))
  room = clearance(s["obstacles"], center, base_yaw, zones)
  room_turned = clearance(s["obstacles"], center, base_yaw + np.pi / 2, zones)
  turn_by_room = room_turned > room + 0.005
  turn_by_pose = torch.abs(_wrap(base_yaw + np.pi / 2 - grip_yaw, np.pi)) < torch.abs(_wrap(base_yaw - grip_yaw, np.pi))
  if prefer_current:
    near, other = torch.where(turn_by_pose, room_turned, room), torch.where(turn_by_pose, room, room_turned)
    turn_by_room = turn_by_pose ^ ((near < 0.01) & (other > near + 0.005))
  turn = torch.where(choosing, turn_by_room, turn_by_pose)
  want = base_yaw + turn.float() * (np.pi / 2)
  return grip_yaw + _wrap(want - grip_yaw, np.pi), grip_yaw


class GraspExpert(Expert):
  """Shared approach / descend / grasp for pick and place; subclasses carry the cube.

  The phase is read off the state: the cube held (closed fingers in contact) means CARRY; the tcp at the grasp
  point, or the fingers closing around the cube, CLOSE; otherwise the tcp goes down a funnel over the cube (open):
  its target is above the grasp point by a height that grows smoothly with the tcp's distance from the cube in the
  table plane and with its yaw error (FUNNEL), DESCEND where that height is under half the approach height, APPROACH
  above it. So a tcp pushed off the axis rises a little and comes back rather than jumping to the approach height,
  and the expert still succeeds when its actions carry noise (benchmarks/expert_success.py --noise). It grasps the
  cube by the face pair nearer the gripper's current yaw unless that side is crowded, and turns proportionally
  (ROT_GAIN), so its rotation is a smooth function of the state rather than a saturated one whose sign flips.
  """
  APPROACH, DESCEND, CLOSE, CARRY = 0, 1, 2, 3
  APPROACH_HEIGHT = 0.08   # m above the grasp point, away from the cube
  FUNNEL = ((0.01, 0.03), (0.1, 0.3))     # (full descent at or below, approach height from): xy error m, yaw rad
  ROT_GAIN = 0.25   # rotation action per 0.1 rad of error: proportional below 0.4 rad
  OPENED = 0.07   # finger opening (m) above which the gripper counts as open (fully open is about 0.08)

  def _grasp_phases(self, s):
    """(target_p [N, 3], yaw [N], gripper [N], phase [N]) of the grasp; phase CARRY where the cube is held."""
    tcp, cube = s["tcp_p"], s["cube_p"]
    cube_yaw = _yaw(rc.quaternion_to_matrix(s["cube_q"]))
    grasp_at = cube.clone()
    grasp_at[:, 2] = torch.clamp(cube[:, 2] - 0.004, min=0.014)
    xy_err = torch.linalg.norm(tcp[:, :2] - cube[:, :2], dim=1)
    yaw, grip_yaw = _pick_yaw(s, cube[:, :2], cube_yaw, OPEN_ZONES, choosing=xy_err > self.FUNNEL[0][1],
                              prefer_current=True)
    yaw_err = torch.abs(_wrap(yaw - grip_yaw, 2 * np.pi))
    (xy_lo, xy_hi), (yaw_lo, yaw_hi) = self.FUNNEL
    rise = torch.maximum(torch.clamp((xy_err - xy_lo) / (xy_hi - xy_lo), 0, 1),
                         torch.clamp((yaw_err - yaw_lo) / (yaw_hi - yaw_lo), 0, 1))
    funnel = grasp_at.clone()
    funnel[:, 2] = grasp_at[:, 2] + self.APPROACH_HEIGHT * rise

    held = s["grasped"] & (s["gripper"] > 0.004)
    at_grasp = torch.linalg.norm(tcp - grasp_at, dim=1) < 0.015
    closing = (s["gripper"] < self.OPENED) & (s["gripper"] > 0.004) & (torch.linalg.norm(tcp - cube, dim=1) < 0.02)
    phase = torch.full_like(xy_err, self.APPROACH, dtype=torch.long)
    phase = torch.where(rise < 0.5, self.DESCEND, phase)
    phase = torch.where(at_grasp | closing, self.CLOSE, phase)
    phase = torch.where(held, self.CARRY, phase)

    target = torch.where((phase <= self.DESCEND)[:, None], funnel, grasp_at)
    gripper = torch.where(phase >= self.CLOSE, CLOSED, OPEN)
    return target, yaw, gripper, phase


class PickExpert(GraspExpert):
  """Grasps the cube and brings it to the task's fixed goal, then holds it there."""

  def _act(self, s):
    target, yaw, gripper, phase = self._grasp_phases(s)
    carry = phase == self.CARRY
    # Aim the cube (not the tcp) at the goal; first lift straight up.
    offset = s["tcp_p"] - s["cube_p"]
    carry_target = s["goal_p"] + offset
    low = s["cube_p"][:, 2] < 0.06
    lift = s["tcp_p"].clone()
    lift[:, 2] = s["goal_p"][:, 2]
    carry_target = torch.where(low[:, None], lift, carry_target)
    target = torch.where(carry[:, None], carry_target, target)
    max_step = torch.where(carry, 0.4, 0.6)
    return _servo_rows(s, target, yaw, gripper, max_step, self.ROT_GAIN), phase


class PlaceExpert(GraspExpert):
  """Grasps the cube, carries it high over the bin, lowers it below the rim, opens, then retreats up.

  Held and away from the bin: CARRY (straight up) below the carry height, OVER (toward the bin) above it; held over
  the bin: LOWER, and open (RELEASE) at the release height; released inside the bin: hold still until the fingers
  are open (RELEASE), then RETREAT up. A cube neither held nor in the bin is grasped again.
  """
  OVER, LOWER, RELEASE, RETREAT = 4, 5, 6, 7
  CARRY_HEIGHT = 0.16
  RELEASE_HEIGHT = 0.065   # cube center above the table at release (bin rim at 0.05)
  INNER_HALF = 0.045       # the bin's inner half side (tasks.PlaceEnv.INNER_HALF)

  def _act(self, s):
    target, yaw, gripper, phase = self._grasp_phases(s)
    tcp, cube, goal = s["tcp_p"], s["cube_p"], s["goal_p"]
    offset = tcp - cube
    xy_err = torch.linalg.norm(cube[:, :2] - goal[:, :2], dim=1)
    held = phase == self.CARRY
    in_bin = ~held & torch.all(torch.abs(cube[:, :2] - goal[:, :2]) < self.INNER_HALF, dim=1) & (cube[:, 2] < 0.09)
    over = xy_err < 0.015
    at_release = torch.abs(cube[:, 2] - self.RELEASE_HEIGHT) < 0.01
    high = cube[:, 2] > self.CARRY_HEIGHT - 0.04
    phase = torch.where(held & ~over & high, self.OVER, phase)
    phase = torch.where(held & over, self.LOWER, phase)
    phase = torch.where(held & over & at_release, self.RELEASE, phase)
    phase = torch.where(in_bin, torch.where(s["gripper"] < self.OPENED, self.RELEASE, self.RETREAT), phase)

    high_over = goal.clone()
    high_over[:, 2] = self.CARRY_HEIGHT
    low_over = goal.clone()
    low_over[:, 2] = self.RELEASE_HEIGHT
    lift = tcp.clone()
    lift[:, 2] = self.CARRY_HEIGHT + offset[:, 2]
    retreat = tcp.clone()
    retreat[:, 2] = 0.2
    for p, where in ((self.CARRY, lift), (self.OVER, high_over + offset), (self.LOWER, low_over + offset),
                     (self.RELEASE, tcp), (self.RETREAT, retreat)):
      target = torch.where((phase == p)[:, None], where, target)
    gripper = torch.where(phase >= self.RELEASE, OPEN, gripper)
    max_step = torch.where(phase == self.LOWER, 0.25, torch.where(phase >= self.CARRY, 0.4, 0.6))
    return _servo_rows(s, target, yaw, gripper, max_step, self.ROT_GAIN), phase


class PushExpert(Expert):
  """Closes the gripper, goes behind the cube (seen from the target), descends and pushes it onto the target.

  The phase is read off the state: the tcp low and on the line behind the cube means PUSH; the tcp within 1.5 cm
  (in the table plane) of the point behind the cube, DESCEND; anything else ABOVE (move over that point).
  """
  ABOVE, DESCEND, PUSH = 0, 1, 2
  PUSH_HEIGHT = 0.018
  BEHIND = CUBE_HALF + 0.03

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

    on_line = (torch.abs(lateral) <= 0.012) & (along <= -CUBE_HALF + 0.002) & (along >= -self.BEHIND - 0.015)
    low = tcp[:, 2] < self.PUSH_HEIGHT + 0.01
    near_pre = torch.linalg.norm(tcp[:, :2] - pre, dim=1) < 0.015
    phase = torch.full_like(along, self.ABOVE, dtype=torch.long)
    phase = torch.where(near_pre, self.DESCEND, phase)
    phase = torch.where(on_line & low, self.PUSH, phase)

    target = torch.where((phase == self.ABOVE)[:, None], pre_high,
                         torch.where((phase == self.DESCEND)[:, None], pre_low, push))
    # Fingers closing across the push (a wide pusher), unless the hand then hits a tall distractor beside the path.
    across = torch.atan2(d[:, 1], d[:, 0])
    yaw, _ = _pick_yaw(s, pre, across, CLOSED_ZONES, choosing=phase == self.ABOVE)
    max_step = torch.where(phase == self.PUSH, 0.25, 0.6)
    return _servo_rows(s, target, yaw, torch.full_like(yaw, CLOSED), max_step), phase


def _servo_rows(s, target, yaw, gripper, max_step, rot_gain: float = 1.0) -> torch.Tensor:
  """`servo` with a per-env gripper [N] and max_step [N]."""
  action = servo(s["tcp_p"], s["tcp_q"], target, yaw, 0.0, max_step=1.0, rot_gain=rot_gain)
  step = action[:, :3]
  norm = torch.linalg.norm(step, dim=1, keepdim=True).clamp(min=1e-9)
  action[:, :3] = step * torch.clamp(max_step[:, None] / norm, max=1.0)
  action[:, 6] = torch.as_tensor(gripper, dtype=action.dtype)
  return action


EXPERTS = {"push": PushExpert, "pick": PickExpert, "place": PlaceExpert}


def make_expert(task: str, num_envs: int, device="cpu") -> Expert:
  """The oracle expert of `task` for `num_envs` parallel envs."""
  return EXPERTS[task](num_envs, device)
