"""The privileged state vector stored with every step (`steps/observation/state`): one fixed layout, pure numpy.

It is read from the same simulator state the oracle experts act on (`RoboShapeEnv.privileged_state`), so it is
what a policy would need to imitate the experts perfectly: the upper bound of any learned representation.
Positions are metres in the world frame (robot base at x = -0.615), quaternions wxyz, joints radians.
"""
import numpy as np

MAX_DISTRACTORS = 8   # EnvSpec refuses more; the distractor rows are padded to this count
# (name, width, description), in order; the dataset's feature doc and the README's table come from here.
FIELDS = (
    ("tcp_pos", 3, "tool centre point position"),
    ("tcp_quat", 4, "tool centre point orientation (wxyz)"),
    ("gripper", 1, "finger opening (m; about 0.08 open, 0 shut)"),
    ("arm_qpos", 7, "the arm's seven joint angles"),
    ("cube_pos", 3, "red cube position"),
    ("cube_quat", 4, "red cube orientation (wxyz)"),
    ("goal_pos", 3, "goal position: push target centre, pick point or bin centre"),
    ("distractors", 5 * MAX_DISTRACTORS,
     f"per distractor (padded to {MAX_DISTRACTORS}): x, y, z, size (m), present (1) or padding (0)"),
)
DIM = sum(width for _, width, _ in FIELDS)


def slices() -> dict:
  """name -> slice of the vector."""
  out, start = {}, 0
  for name, width, _ in FIELDS:
    out[name] = slice(start, start + width)
    start += width
  return out


def describe() -> str:
  """One line per field, with its index range."""
  return "; ".join(f"[{s.start}:{s.stop}] {name}: {text}"
                   for (name, _, text), s in zip(FIELDS, slices().values()))


def pack(tcp_pos, tcp_quat, gripper, arm_qpos, cube_pos, cube_quat, goal_pos, distractors,
         present=None) -> np.ndarray:
  """float32 [N, DIM] from per-env arrays ([N, width] each; distractors [N, K, 4] of x, y, z, size with K <= 8,
  `present` bool [N, K] marking real rows (default: all))."""
  distractors = np.asarray(distractors, np.float32)
  n, k = distractors.shape[:2]
  present = np.ones((n, k), bool) if present is None else np.asarray(present, bool)
  if k > MAX_DISTRACTORS:
    raise ValueError(f"{k} distractors; the state vector holds at most {MAX_DISTRACTORS}")
  rows = np.zeros((n, MAX_DISTRACTORS, 5), np.float32)
  rows[:, :k, :4] = distractors * present[..., None]
  rows[:, :k, 4] = present
  parts = [tcp_pos, tcp_quat, np.reshape(gripper, (n, 1)), arm_qpos, cube_pos, cube_quat, goal_pos,
           rows.reshape(n, -1)]
  out = np.concatenate([np.asarray(p, np.float32).reshape(n, -1) for p in parts], axis=1)
  assert out.shape[1] == DIM, out.shape
  return out
