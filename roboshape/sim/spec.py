"""EnvSpec: what a simulator worker builds. Pure python: importing it never imports the simulator."""
import dataclasses
import numbers
from typing import Iterable, List, Optional, Tuple

from roboshape import envs
from roboshape.envs import camera
from roboshape.errors import UserError

MAX_SEED = 2**31 - 1
# the frame dict's keys that come from a camera: an env reset with render False returns them as zeros
CAMERA_KEYS = camera.all_keys(camera.CAMERAS)


@dataclasses.dataclass(frozen=True)
class EnvSpec:
  """One RoboShape environment: task, generalization level and camera.

  max_episode_steps: 0 uses the task's own horizon (>= 1.5x the expert's 95th-percentile episode length).
  sim_backend: "physx_cpu" or "physx_cuda" (the physics on a GPU); either way a worker owns one env.
  depth: also render the cameras' depth (uint16 millimetres), stored with collected episodes.
  cameras: the cameras rendered (roboshape/envs/camera.py), the front one among them.
  """
  task: str
  level: str = "train"
  resolution: int = 64
  min_distractors: int = 1
  max_distractors: int = 4
  max_episode_steps: int = 0
  sim_backend: str = "physx_cpu"
  depth: bool = False
  cameras: Tuple[str, ...] = camera.DEFAULT

  def __post_init__(self):
    try:
      envs.check_args(self.task, self.level, self.resolution)
      object.__setattr__(self, "cameras", camera.check(self.cameras))
    except ValueError as e:
      raise UserError(str(e)) from None
    for name in ("min_distractors", "max_distractors", "max_episode_steps"):
      value = getattr(self, name)
      if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
        raise UserError(f"env.{name} must be an int >= 0, got {value!r}.")
    if self.min_distractors > self.max_distractors:
      raise UserError(f"env.min_distractors ({self.min_distractors}) exceeds env.max_distractors "
                      f"({self.max_distractors}); set min <= max.")
    if self.max_distractors > 8:
      raise UserError(f"env.max_distractors={self.max_distractors} does not fit the table; use at most 8.")
    if self.sim_backend not in ("physx_cpu", "physx_cuda", "cpu", "gpu"):
      raise UserError(f"unknown env.sim_backend {self.sim_backend!r}; use physx_cpu (or physx_cuda on a GPU).")

  @classmethod
  def from_config(cls, config, level: Optional[str] = None) -> "EnvSpec":
    """The spec of `config.task` with the fields of `config.env`, under `level` (default "train")."""
    env = config.env
    return cls(task=config.task, level=level or "train", resolution=int(env.resolution),
               min_distractors=int(env.min_distractors), max_distractors=int(env.max_distractors),
               max_episode_steps=int(env.max_episode_steps), sim_backend=str(env.sim_backend),
               depth=bool(env.depth), cameras=tuple(env.cameras))


def check_seeds(seeds: Iterable) -> List[int]:
  """The seeds as a list of python ints; UserError for anything that is not an int in [0, 2**31)."""
  out = []
  for seed in seeds:
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
      raise UserError(f"seed {seed!r} is not an int; seeds are ints in [0, {MAX_SEED}].")
    if not 0 <= int(seed) <= MAX_SEED:
      raise UserError(f"seed {seed} out of range; seeds are ints in [0, {MAX_SEED}].")
    out.append(int(seed))
  return out
