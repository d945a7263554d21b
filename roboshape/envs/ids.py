"""The object ids of RoboShape's segmentation maps (`steps/observation/segmentation`), pure numpy.

  0 backdrop (floor and wall), 1 table, 2 robot arm, 3 the red cube, 4 the goal (push target or bin),
  5..12 distractors 0..7, 13 the robot's hand (palm and both fingers).

The hand is its own id so that a ground-truth object decomposition says where the gripper is (the `objects` control
needs it: the paper's policies get no proprioception). Scores of a learned decomposition (FG-ARI, mIoU) count the
robot as one object: `robot_as_one` maps the hand onto the arm first. Datasets collected before roboshape-envs-5
have no id 13 (their robot is id 2 throughout).
"""
import numpy as np

from roboshape.envs.state import MAX_DISTRACTORS

BACKDROP, TABLE, ROBOT, CUBE, GOAL, FIRST_DISTRACTOR = 0, 1, 2, 3, 4, 5
HAND = FIRST_DISTRACTOR + MAX_DISTRACTORS   # 13
NUM_IDS = HAND + 1
HAND_LINKS = ("panda_hand", "panda_leftfinger", "panda_rightfinger", "panda_leftfinger_pad", "panda_rightfinger_pad")
# Display colours, one per id (browse, contact sheet).
COLOURS = np.array([
    [20, 20, 20], [120, 120, 120], [240, 240, 240], [230, 40, 40], [40, 200, 70],
    [60, 110, 240], [240, 200, 40], [200, 80, 220], [40, 210, 210], [250, 140, 40], [150, 90, 50],
    [128, 0, 255], [0, 128, 128], [255, 170, 200],
], np.uint8)


def colorize(segmentation: np.ndarray) -> np.ndarray:
  """uint8 ids [..., H, W] -> uint8 RGB [..., H, W, 3] (ids beyond NUM_IDS wrap around)."""
  return COLOURS[np.asarray(segmentation).astype(np.int64) % len(COLOURS)]


def robot_as_one(segmentation):
  """The segmentation with the hand's pixels given the arm's id (the robot as one object), same dtype and array
  kind: a numpy array for numpy input, a JAX array (traced ones too, as in a jitted encoder step) for JAX input."""
  if not hasattr(segmentation, "dtype"):
    segmentation = np.asarray(segmentation)
  return (segmentation + (segmentation == HAND) * (ROBOT - HAND)).astype(segmentation.dtype)
