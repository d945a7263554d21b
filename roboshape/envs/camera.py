"""The front camera's placement and its pinhole model, pure numpy: where a world point lands in the image.

The scene (roboshape/envs/scene.py) places the camera with ManiSkill's look-at at EYE, looking at TARGET, with the
vertical field of view FOV on a square image. Its frame is SAPIEN's: x forward (the optical axis), y left, z up.
Image coordinates are those of the `objects` tokens (roboshape/encoders/objects.py): row and column mapped to
[-1, 1] over the frame's extent (row -1 at the top), whatever the resolution; depth is the distance along the
optical axis in metres, what the simulator's depth image holds.

  row, col, depth = camera.project(points)     # world [..., 3] -> each [...]
  points = camera.unproject(row, col, depth)   # the inverse, for points in front of the camera
"""
import numpy as np

EYE = (0.42, 0.0, 0.34)
TARGET = (-0.16, 0.0, 0.02)
FOV = 0.95                  # radians, vertical


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
