"""Colors, sizes and generalization levels of the RoboShape world (the paper's exact RGB values).

Pure python + numpy: the parent process imports this to validate a level without importing the simulator.

A level names what a reset draws from:
  train: training distractor colors, training backgrounds, training distractor sizes.
  L1:    unseen distractor colors (backgrounds and sizes as in training).
  L2:    unseen background colors (distractor colors and sizes as in training).
  L3:    novel distractor sizes, both smaller and bigger than in training (colors as in training).
"""
import dataclasses
from typing import Dict, Tuple

import numpy as np

RGB = Tuple[int, int, int]

TRAIN_DISTRACTOR_COLORS: Dict[str, RGB] = {
    "gray": (87, 87, 87),
    "blue": (42, 75, 215),
    "green": (29, 105, 20),
    "brown": (129, 74, 25),
    "cyan": (41, 208, 208),
    "purple": (246, 0, 220),
    "yellow": (255, 238, 51),
}
TRAIN_BACKGROUNDS: Dict[str, RGB] = {
    "red": (245, 39, 39),
    "green": (39, 245, 39),
    "blue": (39, 39, 245),
    "white": (245, 245, 245),
    "black": (10, 10, 10),
}
L1_DISTRACTOR_COLORS: Dict[str, RGB] = {
    "pink": (243, 139, 197),
    "orange": (246, 138, 0),
    "lime": (129, 197, 122),
    "black": (10, 10, 10),
    "dark_green": (0, 90, 41),
    "dark_blue": (0, 28, 90),
    "dark_red": (90, 0, 0),
}
L2_BACKGROUNDS: Dict[str, RGB] = {
    "yellow": (245, 245, 39),
    "pink": (245, 39, 245),
    "cyan": (39, 245, 245),
    "orange": (246, 138, 0),
    "dark_green": (0, 90, 41),
}
TABLE_COLORS: Dict[str, RGB] = {"black": (10, 10, 10), "white": (245, 245, 245)}
CUBE_COLOR: RGB = (255, 0, 0)         # the red cube every task manipulates
GOAL_COLOR: RGB = (40, 190, 70)       # the push target region and the place bin

SHAPES = ("cube", "sphere", "cylinder")
# Distractor size = half the object's width (cube half side, sphere / cylinder radius), meters.
# The red cube's half side is 0.02.
TRAIN_SIZE_RANGE = (0.016, 0.028)
L3_SIZE_RANGES = ((0.008, 0.012), (0.034, 0.042))  # smaller and bigger than anything seen in training


@dataclasses.dataclass(frozen=True)
class Level:
  """What one generalization level samples from."""
  name: str
  distractor_colors: Dict[str, RGB]
  backgrounds: Dict[str, RGB]
  size_ranges: Tuple[Tuple[float, float], ...]

  def sample_size(self, rng: np.random.Generator) -> float:
    """One distractor size (meters) drawn uniformly from one of the level's ranges (ranges picked by width)."""
    widths = np.array([hi - lo for lo, hi in self.size_ranges])
    lo, hi = self.size_ranges[rng.choice(len(widths), p=widths / widths.sum())]
    return float(rng.uniform(lo, hi))


LEVELS: Dict[str, Level] = {
    "train": Level("train", TRAIN_DISTRACTOR_COLORS, TRAIN_BACKGROUNDS, (TRAIN_SIZE_RANGE,)),
    "L1": Level("L1", L1_DISTRACTOR_COLORS, TRAIN_BACKGROUNDS, (TRAIN_SIZE_RANGE,)),
    "L2": Level("L2", TRAIN_DISTRACTOR_COLORS, L2_BACKGROUNDS, (TRAIN_SIZE_RANGE,)),
    "L3": Level("L3", TRAIN_DISTRACTOR_COLORS, TRAIN_BACKGROUNDS, L3_SIZE_RANGES),
}
LEVEL_NAMES = tuple(LEVELS)


def get_level(name: str) -> Level:
  """The Level called `name`; ValueError naming the valid ones otherwise."""
  if name not in LEVELS:
    raise ValueError(f"unknown level {name!r}; choose one of {', '.join(LEVELS)}.")
  return LEVELS[name]


def rgba(color: RGB) -> np.ndarray:
  """The float RGBA a render material takes for an 8-bit sRGB color: linear intensities in [0, 1].

  The renderer writes sRGB-encoded images, so an emissive surface of rgba(c) renders as c itself.
  """
  srgb = np.asarray(color, np.float64) / 255.0
  linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
  return np.concatenate([linear, [1.0]])
