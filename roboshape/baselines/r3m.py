"""R3M: the frozen ResNet of the official R3M checkpoints, run in Flax.

  enc = load_encoder(config.baselines.r3m, resolution=64)
  tokens, _ = enc.step(enc.params, enc.init_state(B), frames)   # uint8 [B, H, W, 3] -> float32 [B, 1, D]

The official `model.pt` is a dict whose "r3m" entry is the state_dict of a DataParallel-wrapped model: the visual
ResNet under "module.convnet.", language heads beside it (ignored). Preprocessing is R3M's own: pixels in
[0, 255] are scaled to [0, 1], resized to 224 x 224 and ImageNet-normalised inside the encoder. D = 512 for
ResNet-18/34 and 2048 for ResNet-50.
"""
import functools
import os

import jax
import jax.numpy as jnp

from roboshape.baselines import convert
from roboshape.baselines import preprocess
from roboshape.baselines import resnet
from roboshape.errors import UserError
from roboshape.models.encoder import FrozenEncoder

MIN_SIDE = 32      # the smallest input side the network takes
DOWNLOAD_PAGE = "https://github.com/facebookresearch/r3m (load_r3m downloads it; or fetch model.pt by hand)"
_PREFIX = "module.convnet."
_NAMES = {"resnet18": "R3M ResNet-18", "resnet34": "R3M ResNet-34", "resnet50": "R3M ResNet-50"}


def default_path(arch: str) -> str:
  """Where the R3M package caches its weights: ~/.r3m/r3m_{18,34,50}/model.pt."""
  return os.path.join(os.path.expanduser("~"), ".r3m", f"r3m_{arch[len('resnet'):]}", "model.pt")


def weights_path(cfg) -> str:
  """The weight file config.baselines.r3m names: its path, or `default_path(arch)` where path is ""."""
  return os.path.expanduser(cfg.path) if cfg.path else default_path(cfg.arch)


def check_weights(cfg) -> None:
  """Raises UserError when `weights_path(cfg)` is not a file (reads nothing; `load_encoder` checks the contents)."""
  convert.check_file(weights_path(cfg), what=_NAMES.get(cfg.arch, "R3M"), download=DOWNLOAD_PAGE)


# The batch runs through the ResNet as this many independent slices. XLA's CPU backend executes independent
# convolutions concurrently, which keeps the cores busier than one convolution split across them (the gain on the
# 2-core CPU: results/small/README.md). Every frame's numbers are unchanged; the graph is this many times larger.
_PARALLEL_SLICES = 4


def _step(model, input_size, params, state, frames):
  """uint8 [B, H, W, 3] -> (tokens float32 [B, 1, D], state)."""
  x = preprocess.imagenet_input(frames, input_size)
  size = max(1, -(-x.shape[0] // _PARALLEL_SLICES))
  if size >= x.shape[0]:
    features = model.apply(params, x)
  else:
    features = jnp.concatenate([model.apply(params, x[i:i + size]) for i in range(0, x.shape[0], size)], axis=0)
  return features[:, None, :], state


def load_params(path: str, arch: str):
  """(ResNet module, Flax variables {"params", "batch_stats"}) from an official R3M model.pt."""
  what = _NAMES[arch]
  state = convert.load_state(path, what=what, download=DOWNLOAD_PAGE)
  if "r3m" not in state:
    keys = ", ".join(sorted(map(str, state))[:6])
    raise UserError(f"{path} is not an R3M checkpoint: it has no 'r3m' entry (its keys: {keys})")
  tensors = convert.to_numpy(state["r3m"], prefix=_PREFIX)
  model = resnet.resnet(arch)
  template = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 64, 64, 3), jnp.float32))
  convert.check_keys(tensors, template, path=path, what=what)
  return model, convert.to_flax(tensors, template)


def load_encoder(cfg, resolution: int) -> FrozenEncoder:
  """The frozen R3M encoder of `cfg` (config.baselines.r3m: arch, path, input_size) for square frames.

  Args:
    cfg: arch is "resnet18", "resnet34" or "resnet50"; path "" means `default_path(arch)`; input_size is the
      side frames are resized to (224, as R3M was trained; 0 keeps the frames' own size).
    resolution: the side of the frames the encoder will see.

  Raises:
    UserError: unknown arch, a missing weight file, or a file of another model.
  """
  if cfg.arch not in resnet.ARCHS:
    raise UserError(f"unknown R3M arch {cfg.arch!r}; choose one of {', '.join(resnet.ARCHS)}")
  input_size = int(cfg.input_size)
  if (input_size or resolution) < MIN_SIDE:
    raise UserError(f"R3M needs inputs of at least {MIN_SIDE} x {MIN_SIDE} pixels, got {input_size or resolution}")
  path = weights_path(cfg)
  _, variables = load_params(path, cfg.arch)
  # Inference BatchNorm is an affine map per channel: folded into the convs once here, it costs nothing per step.
  model, params = resnet.resnet(cfg.arch, folded=True), resnet.fold_batchnorm(variables)
  return FrozenEncoder(
      name="r3m",
      params=params,
      step=functools.partial(_step, model, input_size),
      init_state=lambda batch_size: (),
      num_tokens=1,
      token_dim=resnet.output_dim(cfg.arch),
      identity=convert.file_identity(path, cfg.arch, f"input{input_size or resolution}"),
  )
