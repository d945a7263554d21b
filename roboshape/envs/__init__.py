"""The RoboShape world: three randomized ManiSkill tasks (push, pick, place), their levels and oracle experts.

Importing this package does not import the simulator; `make_env` does (in a worker process, never next to
TensorFlow). Modules: palettes (colors and levels, pure numpy), milestones (each task's steps to success, by name),
scene (the shared ManiSkill scene), tasks (the three task classes), experts (batched oracle experts), contact_sheet
(a PNG of every task under every level).
"""
from roboshape.envs.milestones import MILESTONES  # pylint: disable=unused-import  (the package's name for it)
from roboshape.envs.palettes import LEVEL_NAMES

TASKS = ("push", "pick", "place")
ENV_VERSION = "roboshape-envs-5"   # bumps whenever what a seed produces changes
MIN_RESOLUTION, MAX_RESOLUTION = 16, 512


def check_args(task: str, level: str, resolution: int = 64) -> None:
  """Raises ValueError with a message that says what to do when a task, level or resolution is invalid."""
  if task not in TASKS:
    raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASKS)}.")
  if level not in LEVEL_NAMES:
    raise ValueError(f"unknown level {level!r}; choose one of {', '.join(LEVEL_NAMES)}.")
  if (isinstance(resolution, bool) or not isinstance(resolution, int)
      or not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
    raise ValueError(f"camera resolution {resolution!r} not supported; use an int in "
                     f"[{MIN_RESOLUTION}, {MAX_RESOLUTION}] (64 by default: the paper states no camera resolution).")


def explain_construction_error(e: BaseException) -> str:
  """A one-line message that says what to do when building an env failed with `e`."""
  lines = str(e).strip().splitlines()
  cause = f"{type(e).__name__}: {lines[0] if lines else ''}"
  if any(key in str(e) for key in ("rendering device", "Vulkan", "vk::")):
    return ("SAPIEN found no Vulkan rendering device; run `make setup` (installs Mesa >= 24.3 on Debian 12) "
            f"and check `python -m roboshape.sim.probe` ({cause})")
  return f"cannot build the RoboShape env: {cause}"


def make_env(task: str, level: str = "train", resolution: int = 64, obs_mode: str = "rgb+segmentation",
             min_distractors: int = 1, max_distractors: int = 4, num_envs: int = 1,
             sim_backend: str = "physx_cpu", **kwargs):
  """A ManiSkill env of `task` under `level`, controlled by pd_ee_delta_pose (7-D actions in [-1, 1]).

  Use `env.unwrapped` for the task object (privileged_state, frames, HORIZON). Imports the simulator.
  """
  check_args(task, level, resolution)
  import gymnasium as gym  # pylint: disable=import-outside-toplevel
  from roboshape.envs import tasks  # pylint: disable=import-outside-toplevel  (registers the envs)
  return gym.make(tasks.ENV_IDS[task], obs_mode=obs_mode, control_mode="pd_ee_delta_pose", level=level,
                  resolution=resolution, min_distractors=min_distractors, max_distractors=max_distractors,
                  num_envs=num_envs, sim_backend=sim_backend, render_mode=kwargs.pop("render_mode", None),
                  **kwargs)
