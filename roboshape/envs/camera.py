"""The cameras a scene can render, named here alone, and the front camera's pinhole model, pure numpy.

CAMERAS lists them: "front" (fixed, looking at the table) and "wrist" (mounted on the hand, looking along the
fingers, where ManiSkill's panda_wristcam mounts its camera). A camera's frames go by its prefix (`keys`): the
front view as "image", "segmentation" and "depth" (the names the open robot datasets give their main view), the
wrist view as "wrist_image", "wrist_segmentation" and "wrist_depth"; every layer that stores or shows frames asks
`keys` for them, so a third camera is one entry here (and its mount in roboshape/envs/scene.py).

The front camera's pinhole model says where a world point lands in its image:

The scene (roboshape/envs/scene.py) places the camera with ManiSkill's look-at at EYE, looking at TARGET, with the
vertical field of view FOV on a square image. Its frame is SAPIEN's: x forward (the optical axis), y left, z up.
Image coordinates are those of the `objects` tokens (roboshape/encoders/objects.py): row and column mapped to
[-1, 1] over the frame's extent (row -1 at the top), whatever the resolution; depth is the distance along the
optical axis in metres, what the simulator's depth image holds.

  row, col, depth = camera.project(points)     # world [..., 3] -> each [...]
  points = camera.unproject(row, col, depth)   # the inverse, for points in front of the camera
"""
from typing import Sequence, Tuple

import numpy as np

FRONT, WRIST = "front", "wrist"
CAMERAS = (FRONT, WRIST)
DEFAULT = (FRONT,)          # env.cameras' default: the front camera alone, as every run before the field
FRAME_KEYS = ("image", "segmentation", "depth")   # a camera's frames, the front camera's names
_PREFIX = {FRONT: "", WRIST: "wrist_"}

# The wrist camera: on the hand link, 3.5 cm along its x and 3.6 cm up its z, turned to look along the fingers (+z)
# and shifted 2 cm sideways and 1.15 cm forward, as panda_v3.urdf's camera_link; ManiSkill's vertical FOV for it.
WRIST_LINK = "panda_hand"
WRIST_MOUNT = ((0.035, 0.0, 0.036), (0.0, -1.5707, 3.1415))   # xyz, rpy of the camera's base on the hand
WRIST_OFFSET = (0.0, 0.02, 0.0115)                             # the camera in its base's frame
WRIST_FOV = np.pi / 2

EYE = (0.42, 0.0, 0.34)
TARGET = (-0.16, 0.0, 0.02)
FOV = 0.95                  # radians, vertical


def others(cameras: Sequence[str]) -> Tuple[str, ...]:
  """The cameras of `cameras` beyond the front one, in order (what names a grid's dataset of several cameras)."""
  return tuple(c for c in cameras if c != FRONT)


def rotation() -> np.ndarray:
  """float64 [3, 3]: the camera frame's axes (forward, left, up) as columns, in world coordinates."""
  forward = np.subtract(TARGET, EYE).astype(np.float64)
  forward /= np.linalg.norm(forward)
  left = np.cross((0.0, 0.0, 1.0), forward)
  left /= np.linalg.norm(left)
  up = np.cross(forward, left)
  return np.stack([forward, left, up], axis=1)


def project(points):
  """World points [..., 3] -> (row, col, depth), each [...]: image coordinates in [-1, 1] and metres along the
  optical axis. Works on numpy or jax arrays."""
  r = rotation().astype(np.float32)
  local = (points - np.asarray(EYE, np.float32)) @ r          # [..., 3]: forward, left, up
  scale = np.float32(np.tan(FOV / 2))
  forward = local[..., 0]
  return -local[..., 2] / (forward * scale), -local[..., 1] / (forward * scale), forward


def unproject(row, col, depth):
  """The world points [..., 3] at image coordinates (row, col) and `depth` metres along the optical axis."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  scale = np.float32(np.tan(FOV / 2))
  local = jnp.stack([depth, -col * scale * depth, -row * scale * depth], axis=-1)
  return local @ rotation().T.astype(np.float32) + np.asarray(EYE, np.float32)


def keys(camera: str) -> Tuple[str, str, str]:
  """The frame keys of `camera`: its image, segmentation and depth (FRAME_KEYS with its prefix)."""
  return tuple(_PREFIX[camera] + key for key in FRAME_KEYS)


def all_keys(cameras: Sequence[str]) -> Tuple[str, ...]:
  """Every frame key of `cameras`, camera by camera."""
  return tuple(key for c in cameras for key in keys(c))


def view(observation, camera: str) -> dict:
  """`observation` (an episode or observation dict) as `camera` sees it: that camera's frames under the front
  camera's names ("wrist_image" as "image", ...), every other camera's frames left out, the other keys as they are."""
  frames = set(all_keys(CAMERAS))
  out = {k: v for k, v in observation.items() if k not in frames}
  out.update({front: observation[own] for front, own in zip(FRAME_KEYS, keys(camera)) if own in observation})
  return out


def stored(observation: Sequence[str]) -> Tuple[str, ...]:
  """The cameras whose image is among the keys of `observation` (an episode or observation dict, or its keys), in
  CAMERAS' order."""
  return tuple(c for c in CAMERAS if keys(c)[0] in observation)


def check(cameras: Sequence[str]) -> Tuple[str, ...]:
  """`cameras` as a tuple; ValueError, saying what to do, unless they are distinct names of CAMERAS with the front
  one among them (the encoders read the front view)."""
  cameras = tuple(cameras) if not isinstance(cameras, str) else (cameras,)
  unknown = [c for c in cameras if c not in CAMERAS]
  if unknown or len(set(cameras)) != len(cameras) or "front" not in cameras:
    raise ValueError(f"env.cameras={cameras!r}: use distinct names of {', '.join(CAMERAS)}, with \"front\" among "
                     "them, e.g. (\"front\", \"wrist\").")
  return cameras
