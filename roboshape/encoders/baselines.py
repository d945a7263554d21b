"""R3M and DINO: holistic encoders from their official torch checkpoints (roboshape/baselines).

Each reads its own config section (baselines.r3m, baselines.dino), checked by its `check`: a known architecture and
frames at least the network's smallest side.
"""
from roboshape.encoders import registry
from roboshape import ranges
from roboshape.errors import UserError


def _check_section(config, name: str, archs, min_side: int) -> None:
  """baselines.<name>: a known architecture and frames at least `min_side` pixels a side."""
  section = f"baselines.{name}"
  ranges.check(config, (ranges.Choice(f"{section}.arch", tuple(archs), f"the {name.upper()} network"),
                        ranges.Int(f"{section}.input_size", 0, "the side frames are resized to; 0: their own")))
  input_size = int(config.baselines[name].input_size)
  side = input_size or config.env.resolution
  if side < min_side:
    raise UserError(f"{section}.input_size={input_size} gives {side}x{side} inputs; {name.upper()} needs at least "
                    f"{min_side}: set it to 0 with env.resolution >= {min_side}, or to 224.")


def check_r3m(config) -> None:
  """The baselines.r3m section (imports the network's module, JAX, without starting a backend)."""
  # pylint: disable=import-outside-toplevel
  from roboshape.baselines import r3m
  from roboshape.baselines import resnet
  _check_section(config, "r3m", resnet.ARCHS, r3m.MIN_SIDE)


def check_dino(config) -> None:
  """The baselines.dino section (imports the network's module, JAX, without starting a backend)."""
  # pylint: disable=import-outside-toplevel
  from roboshape.baselines import dino
  from roboshape.baselines import vit
  _check_section(config, "dino", vit.ARCHS, dino.MIN_SIDE)


def available_r3m(config) -> None:
  """Its weight file is there (roboshape.baselines.r3m.check_weights)."""
  from roboshape.baselines import r3m  # pylint: disable=import-outside-toplevel
  r3m.check_weights(config.baselines.r3m)


def available_dino(config) -> None:
  """Its weight file is there (roboshape.baselines.dino.check_weights)."""
  from roboshape.baselines import dino  # pylint: disable=import-outside-toplevel
  dino.check_weights(config.baselines.dino)


def _r3m(config, workdir: str):
  del workdir
  from roboshape.baselines import r3m  # pylint: disable=import-outside-toplevel
  return r3m.load_encoder(config.baselines.r3m, resolution=config.env.resolution)


def _dino(config, workdir: str):
  del workdir
  from roboshape.baselines import dino  # pylint: disable=import-outside-toplevel
  return dino.load_encoder(config.baselines.dino, resolution=config.env.resolution)


registry.register(registry.Kind(
    name="r3m", inputs=("image",), pretrain="", build=_r3m, title="R3M",
    description="R3M ResNet from the official weights (one global token)",
    sections=("baselines.r3m",), check=check_r3m, available=available_r3m, order=1, views=True,
    tokens=lambda config: f"1 x (2048 for {config.baselines.r3m.arch}; 512 for resnet18/34)"))
registry.register(registry.Kind(
    name="dino", inputs=("image",), pretrain="", build=_dino, title="DINO",
    description="DINO ViT from the official weights (the CLS token, optionally the patch tokens)",
    sections=("baselines.dino",), check=check_dino, available=available_dino, order=0, views=True,
    tokens=lambda config: "1 + patches (patch_tokens=True)" if config.baselines.dino.patch_tokens else "1 (CLS)"))
