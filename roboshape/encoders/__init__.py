"""The encoder registry: every frozen encoder a policy can be trained on, registered by name.

An encoder is one module in this package that calls `register(Kind(...))` when imported: its name, the observation
keys its step reads (`inputs`, any of OBSERVATION_KEYS), whether it has a pretraining stage trained in the run's
workdir, and `build(config, workdir) -> FrozenEncoder`. Configs, the grid, the feature cache, closed-loop
evaluation and the report all take any registered name. Importing this package is cheap: each `build` imports
what it needs (JAX, torch, the model) only when called.

Adding an encoder (README.md, "Adding an encoder"): a module here with its `Kind`, its name in `_MODULES`, and
`configs/{push,pick,place}_<name>.py`.
"""
import dataclasses
import importlib
from typing import Callable, Dict, Tuple

from roboshape.errors import UserError
from roboshape.sim.spec import CAMERA_KEYS

# What the simulator workers and the dataset provide per step (roboshape/data/rlds.py, roboshape/sim/worker.py).
OBSERVATION_KEYS = CAMERA_KEYS + ("state",)


@dataclasses.dataclass(frozen=True)
class Kind:
  """One registered encoder.

  Attributes:
    name: the config's `encoder` value and the column name in tables.
    inputs: observation keys the encoder's step reads, e.g. ("image",) or ("state",).
    pretrain: the module whose `run(config, workdir, make_validation)` is the `pretrain` stage that trains it in
      the run's workdir ("roboshape.train.pretrain" for SAVi); "" for an encoder built from fixed weights or from
      no weights.
    build: (config, workdir) -> roboshape.models.encoder.FrozenEncoder.
    title: the name tables print ("SAVi").
    description: one line for the README and error messages.
    evaluator: for an encoder with a pretrain stage, the module (in roboshape/eval/) whose
      `validation(config, root, model, episodes)` scores it during pretraining ("roboshape.eval.slots" for SAVi:
      FG-ARI and mIoU); "" for none. roboshape/stages.py hands it to the pretrain stage.
  """
  name: str
  inputs: Tuple[str, ...]
  pretrain: str
  build: Callable
  title: str
  description: str
  evaluator: str = ""

  def __post_init__(self):
    unknown = [k for k in self.inputs if k not in OBSERVATION_KEYS]
    if unknown or not self.inputs:
      raise ValueError(f"encoder {self.name!r}: inputs {self.inputs} must be a non-empty subset of {OBSERVATION_KEYS}")


_REGISTRY: Dict[str, Kind] = {}
# The modules that register the built-in encoders, imported on first use.
_MODULES = ("roboshape.encoders.savi", "roboshape.encoders.baselines", "roboshape.encoders.state",
            "roboshape.encoders.objects", "roboshape.encoders.ae")


def register(kind: Kind) -> Kind:
  """Adds `kind` to the registry (a second registration of a name replaces the first)."""
  _REGISTRY[kind.name] = kind
  return kind


def _load() -> None:
  for module in _MODULES:
    importlib.import_module(module)


def names() -> Tuple[str, ...]:
  """Every registered encoder name, in registration order."""
  _load()
  return tuple(_REGISTRY)


def get(name: str) -> Kind:
  """The registered encoder `name`; a UserError naming the choices otherwise."""
  _load()
  if name not in _REGISTRY:
    raise UserError(f"unknown encoder {name!r}; registered encoders: {', '.join(_REGISTRY)} "
                    "(add one as a module in roboshape/encoders/).")
  return _REGISTRY[name]


def build_encoder(config, workdir: str):
  """The `FrozenEncoder` of `config.encoder`, built by its registered `build`; with `config.policy.proprio`, its
  tokens followed by a proprioception token per frame (roboshape/encoders/proprio.py)."""
  encoder = get(config.encoder).build(config, workdir)
  if config.get("policy", {}).get("proprio", False):
    from roboshape.encoders import proprio  # pylint: disable=import-outside-toplevel
    encoder = proprio.with_proprio(encoder)
  return encoder
