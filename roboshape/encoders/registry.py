"""The encoder registry's types and its table of registered encoders (roboshape/encoders/__init__.py says how an
encoder is added). An encoder module imports this one, never the package, so the package can import every built-in
encoder module without an import circle."""
import dataclasses
from typing import Callable, Dict, Optional, Tuple

from roboshape.errors import UserError
from roboshape.sim.spec import CAMERA_KEYS

# What the simulator workers and the dataset provide per step (roboshape/data/rlds.py, roboshape/sim/worker.py).
OBSERVATION_KEYS = CAMERA_KEYS + ("state",)


@dataclasses.dataclass(frozen=True)
class Selection:
  """How the pretrain stage picks one of several seeds' models: by `metric` of each one's final validation."""
  metric: str                    # a key of the validation's metrics (the encoder's evaluator), e.g. "fg_ari"
  higher_is_better: bool
  name: str                      # the metric in messages and figures ("FG-ARI")


@dataclasses.dataclass(frozen=True)
class PretrainModel:
  """What the pretraining loop (roboshape/train/pretrain.py) needs of the model it trains for an encoder.

  Attributes:
    build: config -> the Flax module, from the encoder's own config section, env.resolution and the pretrain
      section (a depth output when pretrain.train.depth_weight > 0). It has an `input_pool` attribute, and its apply
      on float video [B, L, H, W, 3] in [0, 1] (rng stream "slots" given, used or not) returns recon
      [B, L, h, w, 3] with h = H / input_pool, and depth [B, L, h, w] (metres) when it predicts depth.
    selection: how the best of several seeds (pretrain.train_seeds) is chosen, by a metric of the encoder's
      evaluator (Kind.evaluator).
    loss: (module, outputs, frames float [B, L, H, W, 3], depth uint16 [B, L, H, W] or None, depth_weight) ->
      (loss, {term: value}), what the train step minimises; None: the reconstruction MSE of the pretraining loop
      (roboshape/train/pretrain.py, reconstruction_loss).
  """
  build: Callable
  selection: Selection
  loss: Optional[Callable] = None


@dataclasses.dataclass(frozen=True)
class Kind:
  """One registered encoder.

  Attributes:
    name: the config's `encoder` value and the column name in tables.
    inputs: observation keys the encoder's step reads, e.g. ("image",) or ("state",).
    pretrain: the trainer of its `pretrain` stage, which trains it in the run's workdir: a key of
      roboshape/stages.py's PRETRAINERS ("loop", the pretraining loop of roboshape/train/pretrain.py, which trains
      `model`); "" for an encoder built from fixed weights or from no weights.
    build: (config, workdir) -> roboshape.models.encoder.FrozenEncoder.
    title: the name tables print ("SAVi").
    description: one line for the README and error messages.
    evaluator: for an encoder with a pretrain stage, what scores it during pretraining: a key of
      roboshape/stages.py's EVALUATORS, each a `validation(config, root, model, episodes)` in roboshape/eval/
      ("slots" for SAVi: FG-ARI and per-object IoUs); "" for none. roboshape/stages.py hands it to the pretrain
      stage.
    model: what the pretraining loop trains for it (None for an encoder without a pretrain stage).
    sections: the config sections (or single dotted fields) it reads beyond those every run reads, e.g.
      ("pretrain", "savi"), or the AE's ("pretrain", "ae", "savi.slot_size"), whose token width defaults to SAVi's:
      roboshape/config_check.py checks them for this encoder alone, so a value only another encoder needs (SAVi's
      decoder at env.resolution=32) never refuses its runs.
    check: config -> None, raising UserError "<field>=<value>: use ..." for the first bad field of its own
      sections: their ranges (roboshape/ranges.py, declared in its module) and the constraints between them and
      the frames; config_check runs it before any stage, the pretraining loop when it starts. None: nothing to
      check.
    available: config -> None, raising UserError when what the encoder is built from is absent here (its weight
      file), without reading it: the grid asks it of every run before the first starts and skips a baseline that is
      not available at once (roboshape/stages.py). None: nothing to look for.
    baseline: a comparison for the encoder under study (SAVi, the one registered with False): a grid's run of it
      that fails on bad input (e.g. absent weights) is skipped and said in the report, where a failure of the
      encoder under study stops the grid.
    slot_videos: its closed-loop videos also show its slot decomposition beside each frame
      (roboshape/eval/videos.py, SaviSlotVideo).
    family: its part in the paper's question (FAMILIES): "object-centric", the representation under study whose
      claims the verdict tests (roboshape/report/claims.py); "global", what it is compared with in those claims;
      "control", compared with it in the tables, not in the claims (e.g. ground-truth object tokens);
      "privileged", the control that should succeed, named in the verdict.
    order: its column's place in the tables (smaller first; the paper's order, then baselines and controls).
    tokens: config -> "N x D", what one frame becomes for the policy, said without building the encoder (the GPU
      benchmark's projection, benchmarks/gpu_scaleup.py); None: "unknown".
    points: config -> "" when the encoder built for `config` says where each token's object is
      (FrozenEncoder.points, which policy.hand_relative needs), else why not; None: its tokens never do.
    views: with several env.cameras one encoder encodes each view (roboshape/encoders/views.py): its weights read
      any camera's frames (the `objects` control, fixed-weight encoders), or its pretraining learns every view of
      env.cameras (SAVi and the AE: roboshape/train/pretrain.py's clips come from every view). False: it reads the
      front camera alone, and config_check refuses it with several cameras.
  """
  name: str
  inputs: Tuple[str, ...]
  pretrain: str
  build: Callable
  title: str
  description: str
  evaluator: str = ""
  model: Optional[PretrainModel] = None
  sections: Tuple[str, ...] = ()
  check: Optional[Callable] = None
  available: Optional[Callable] = None
  baseline: bool = True
  slot_videos: bool = False
  family: str = "global"
  order: int = 100
  tokens: Optional[Callable] = None
  points: Optional[Callable] = None
  views: bool = False

  def __post_init__(self):
    unknown = [k for k in self.inputs if k not in OBSERVATION_KEYS]
    if unknown or not self.inputs:
      raise ValueError(f"encoder {self.name!r}: inputs {self.inputs} must be a non-empty subset of {OBSERVATION_KEYS}")
    if self.family not in FAMILIES:
      raise ValueError(f"encoder {self.name!r}: family {self.family!r} must be one of {FAMILIES}")


FAMILIES = ("object-centric", "global", "control", "privileged")


_REGISTRY: Dict[str, Kind] = {}


def register(kind: Kind) -> Kind:
  """Adds `kind` to the registry (a second registration of a name replaces the first)."""
  _REGISTRY[kind.name] = kind
  return kind


def unregister(name: str) -> None:
  """Removes the encoder `name` from the registry (a test's toy encoder, after the test)."""
  _REGISTRY.pop(name, None)


def names() -> Tuple[str, ...]:
  """Every registered encoder name, in registration order."""
  return tuple(_REGISTRY)


def get(name: str) -> Kind:
  """The registered encoder `name`; a UserError naming the choices otherwise."""
  if name not in _REGISTRY:
    raise UserError(f"unknown encoder {name!r}; registered encoders: {', '.join(_REGISTRY)} "
                    "(add one as a module in roboshape/encoders/).")
  return _REGISTRY[name]


def in_family(family: str) -> Tuple[str, ...]:
  """The registered encoders of `family` (FAMILIES), in table order."""
  return tuple(n for n in table_order() if _REGISTRY[n].family == family)


def table_order() -> Tuple[str, ...]:
  """Every registered encoder in the order the tables give their columns (Kind.order, then registration)."""
  return tuple(sorted(_REGISTRY, key=lambda n: _REGISTRY[n].order))


def tokens_per_frame(config, name: str) -> str:
  """What one frame becomes for the policy of encoder `name`, "N x D" (Kind.tokens), or "unknown"."""
  kind = get(name)
  return kind.tokens(config) if kind.tokens else "unknown"


def build_encoder(config, workdir: str):
  """The `FrozenEncoder` of `config.encoder`, built by its registered `build`; with several `config.env.cameras`,
  run on each view (roboshape/encoders/views.py); with `config.policy.proprio`, its tokens followed by a
  proprioception token per frame, and with `config.policy.hand_relative` each token's object relative to the hand
  (roboshape/encoders/proprio.py)."""
  from roboshape.encoders import views  # pylint: disable=import-outside-toplevel
  encoder = views.with_views(get(config.encoder).build(config, workdir), config.env.cameras)
  if config.policy.proprio:
    from roboshape.encoders import proprio  # pylint: disable=import-outside-toplevel
    encoder = proprio.with_proprio(encoder, hand_relative=bool(config.policy.hand_relative))
  return encoder
