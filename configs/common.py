"""The pieces every roboshape experiment config is built from.

An experiment file (e.g. `configs/pick_savi.py`) calls `get_config(task, encoder, variant)`; its variant comes from
the command line as `--config=configs/pick_savi.py:tiny`. Variants:

  paper: the paper's scale (2000 demos per task, 100 rollouts x 3 seeds per cell); meant for GPU machines.
  small: a scale that trains and evaluates on a 2-core CPU in hours (200 demos per task).
  tiny:  a handful of episodes and steps, for tests and `make demo`.

Every field can be overridden on the command line, e.g. `--config.policy.train.steps=100`.
Each section below belongs to one part of the code base (named in its function's docstring).
"""
import ml_collections

TASKS = ("push", "pick", "place")
ENCODERS = ("savi", "dino", "r3m")
VARIANTS = ("paper", "small", "tiny")
LEVELS = ("train", "L1", "L2", "L3")
STAGES = ("collect", "pretrain", "cache", "train_policy", "evaluate", "report")


def _pick(variant: str, paper, small, tiny):
  return {"paper": paper, "small": small, "tiny": tiny}[variant]


def env_config(variant: str) -> ml_collections.ConfigDict:
  """The RoboShape world (roboshape/envs): what each reset randomises and what the camera sees."""
  del variant
  return ml_collections.ConfigDict(dict(
      resolution=64,            # square RGB camera in front of the robot, pixels per side
      min_distractors=1,
      max_distractors=4,
      max_episode_steps=0,      # 0: the task's own horizon (>= 1.5x the expert's 95th percentile)
      sim_backend="physx_cpu",  # "physx_cuda" batches envs in one process where a GPU is present
  ))


def sim_config(variant: str) -> ml_collections.ConfigDict:
  """The numpy bridge to the simulator (roboshape/sim)."""
  del variant
  return ml_collections.ConfigDict(dict(
      num_workers=0,            # 0: one worker per CPU core
  ))


def data_config(variant: str) -> ml_collections.ConfigDict:
  """The RoboShape dataset (roboshape/data): expert demos in RLDS/TFDS."""
  return ml_collections.ConfigDict(dict(
      dir="",                   # "": <workdir>/data; set it to share one dataset between experiments
      train_episodes=_pick(variant, 2000, 200, 4),
      val_fraction=0.05,        # validation episodes, from seeds disjoint from the training ones
      min_val_episodes=1,
  ))


def savi_config(variant: str) -> ml_collections.ConfigDict:
  """SAVi, the object-centric video encoder (roboshape/models/savi.py, roboshape/train/pretrain.py)."""
  return ml_collections.ConfigDict(dict(
      num_slots=11,
      slot_size=128,
      train=ml_collections.ConfigDict(dict(
          steps=_pick(variant, 100_000, 3000, 20),
          batch_size=_pick(variant, 64, 8, 2),
          clip_length=6,
      )),
  ))


def baseline_config(variant: str) -> ml_collections.ConfigDict:
  """Frozen global encoders loaded from official checkpoints (roboshape/baselines)."""
  del variant
  return ml_collections.ConfigDict(dict(
      r3m=ml_collections.ConfigDict(dict(arch="resnet50", path="")),
      dino=ml_collections.ConfigDict(dict(arch="vits16", path="")),
  ))


def policy_config(variant: str) -> ml_collections.ConfigDict:
  """The transformer policy with a GMM head, trained by behaviour cloning (roboshape/models, roboshape/train/bc.py)."""
  return ml_collections.ConfigDict(dict(
      history=10,
      train=ml_collections.ConfigDict(dict(
          steps=_pick(variant, 100_000, 5000, 20),
          batch_size=_pick(variant, 256, 64, 4),
      )),
  ))


def eval_config(variant: str) -> ml_collections.ConfigDict:
  """Closed-loop evaluation (roboshape/eval)."""
  return ml_collections.ConfigDict(dict(
      levels=LEVELS,
      rollouts_per_seed=_pick(variant, 100, 20, 2),
      num_seeds=_pick(variant, 3, 3, 1),
  ))


def get_config(task: str, encoder: str, variant: str = "paper") -> ml_collections.ConfigDict:
  """The full config of one experiment: `task` x `encoder` at the scale `variant`."""
  variant = variant or "paper"
  if task not in TASKS:
    raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASKS)}.")
  if encoder not in ENCODERS:
    raise ValueError(f"unknown encoder {encoder!r}; choose one of {', '.join(ENCODERS)}.")
  if variant not in VARIANTS:
    raise ValueError(f"unknown variant {variant!r}; use configs/<exp>.py:<variant> with one of {', '.join(VARIANTS)}.")
  stages = STAGES if encoder == "savi" else tuple(s for s in STAGES if s != "pretrain")
  return ml_collections.ConfigDict(dict(
      name=f"{task}_{encoder}",
      task=task,
      encoder=encoder,
      variant=variant,
      seed=0,
      stages=stages,
      env=env_config(variant),
      sim=sim_config(variant),
      data=data_config(variant),
      savi=savi_config(variant),
      baselines=baseline_config(variant),
      policy=policy_config(variant),
      eval=eval_config(variant),
  ))
