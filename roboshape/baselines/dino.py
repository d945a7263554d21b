"""DINO: the frozen self-supervised ViT of the official DINO checkpoints, run in Flax.

  enc = load_encoder(config.baselines.dino, resolution=64)
  tokens, _ = enc.step(enc.params, enc.init_state(B), frames)   # uint8 [B, H, W, 3] -> float32 [B, N, D]

The official `dino_deitsmall16_pretrain.pth` / `dino_vitbase16_pretrain.pth` hold the backbone's state_dict
(cls_token, pos_embed, patch_embed.proj, blocks.i.*, norm). Frames are scaled to [0, 1], resized to 224 x 224 and
ImageNet-normalised inside the encoder; the token is the final-norm CLS token (N = 1, D = 384 for ViT-S/16,
768 for ViT-B/16), followed by the patch tokens when cfg.patch_tokens is set (N = 1 + (side / 16)^2).
"""
import functools
import os

import jax
import jax.numpy as jnp

from roboshape.baselines import convert
from roboshape.baselines import preprocess
from roboshape.baselines import vit
from roboshape.errors import UserError
from roboshape.models.encoder import FrozenEncoder

MIN_SIDE = 16      # the smallest frame side the network takes (one 16 x 16 patch)
_FILES = {"vits16": "dino_deitsmall16_pretrain", "vitb16": "dino_vitbase16_pretrain"}
_NAMES = {"vits16": "DINO ViT-S/16", "vitb16": "DINO ViT-B/16"}


def download_url(arch: str) -> str:
  name = _FILES[arch]
  return f"https://dl.fbaipublicfiles.com/dino/{name}/{name}.pth"


def default_path(arch: str) -> str:
  """torch hub's checkpoint cache: $TORCH_HOME/hub/checkpoints (TORCH_HOME defaults to ~/.cache/torch)."""
  cache = os.environ.get("XDG_CACHE_HOME", os.path.join(os.path.expanduser("~"), ".cache"))
  torch_home = os.path.expanduser(os.environ.get("TORCH_HOME", os.path.join(cache, "torch")))
  return os.path.join(torch_home, "hub", "checkpoints", f"{_FILES[arch]}.pth")


def weights_path(cfg) -> str:
  """The weight file config.baselines.dino names: its path, or `default_path(arch)` where path is ""."""
  return os.path.expanduser(cfg.path) if cfg.path else default_path(cfg.arch)


def check_weights(cfg) -> None:
  """Raises UserError when `weights_path(cfg)` is not a file (reads nothing; `load_encoder` checks the contents)."""
  download = download_url(cfg.arch) if cfg.arch in _FILES else "https://github.com/facebookresearch/dino"
  convert.check_file(weights_path(cfg), what=_NAMES.get(cfg.arch, "DINO"), download=download)


def _backbone_state(state):
  """The backbone's state_dict from a pretrain file (itself) or a full training checkpoint (its teacher)."""
  if isinstance(state.get("teacher"), dict):
    state = state["teacher"]
  out = {}
  for key, value in state.items():
    if isinstance(key, str):
      for prefix in ("module.", "backbone."):
        key = key[len(prefix):] if key.startswith(prefix) else key
    out[key] = value
  return out


def _step(model, input_size, patch_tokens, params, state, frames):
  """uint8 [B, H, W, 3] -> (tokens float32 [B, N, D], state)."""
  tokens = model.apply(params, preprocess.imagenet_input(frames, input_size))
  return (tokens if patch_tokens else tokens[:, :1]), state


def load_params(path: str, arch: str):
  """(ViT module, Flax variables {"params"}) from an official DINO pretrain .pth file."""
  what = _NAMES[arch]
  state = convert.load_state(path, what=what, download=download_url(arch))
  tensors = convert.to_numpy(_backbone_state(state))
  model = vit.vit(arch)
  template = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 224, 224, 3), jnp.float32))
  convert.check_keys(tensors, template, path=path, what=what, ignore=("head.",))
  return model, convert.to_flax(tensors, template)


def load_encoder(cfg, resolution: int) -> FrozenEncoder:
  """The frozen DINO encoder of `cfg` (config.baselines.dino) for square frames of side `resolution`.

  Args:
    cfg: arch is "vits16" or "vitb16"; path "" means `default_path(arch)`; input_size is the side frames are
      resized to (224, the pretraining size; 0 keeps the frames' own size, the position embeddings are then
      resized to its grid); patch_tokens appends the patch tokens to the CLS token.
    resolution: the side of the frames the encoder will see.

  Raises:
    UserError: unknown arch, a missing weight file, or a file of another model.
  """
  if cfg.arch not in vit.ARCHS:
    raise UserError(f"unknown DINO arch {cfg.arch!r}; choose one of {', '.join(vit.ARCHS)}")
  input_size = int(cfg.input_size)
  side = input_size or resolution
  if side < MIN_SIDE:
    raise UserError(f"DINO needs frames of at least {MIN_SIDE} x {MIN_SIDE} pixels, got {side}")
  patch_tokens = bool(cfg.patch_tokens)
  path = weights_path(cfg)
  model, params = load_params(path, cfg.arch)
  return FrozenEncoder(
      name="dino",
      params=params,
      step=functools.partial(_step, model, input_size, patch_tokens),
      init_state=lambda batch_size: (),
      num_tokens=1 + (side // 16) ** 2 if patch_tokens else 1,
      token_dim=vit.ARCHS[cfg.arch]["embed_dim"],
      identity=convert.file_identity(path, cfg.arch, f"input{side}", f"patches{int(patch_tokens)}"),
  )
