"""R3M and DINO: holistic encoders from their official torch checkpoints (roboshape/baselines)."""
from roboshape import encoders


def _r3m(config, workdir: str):
  del workdir
  from roboshape.baselines import r3m  # pylint: disable=import-outside-toplevel
  return r3m.load_encoder(config.baselines.r3m, resolution=config.env.resolution)


def _dino(config, workdir: str):
  del workdir
  from roboshape.baselines import dino  # pylint: disable=import-outside-toplevel
  return dino.load_encoder(config.baselines.dino, resolution=config.env.resolution)


encoders.register(encoders.Kind(
    name="r3m", inputs=("image",), pretrain="", build=_r3m, title="R3M",
    description="R3M ResNet from the official weights (one global token)"))
encoders.register(encoders.Kind(
    name="dino", inputs=("image",), pretrain="", build=_dino, title="DINO",
    description="DINO ViT from the official weights (the CLS token, optionally the patch tokens)"))
