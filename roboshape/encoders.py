"""Builds the frozen encoder a config names: SAVi from the run's own checkpoint, R3M or DINO from official weights."""
from roboshape.models.encoder import FrozenEncoder


def build_encoder(config, workdir: str) -> FrozenEncoder:
  """The `FrozenEncoder` for `config.encoder` ("savi", "r3m" or "dino")."""
  # pylint: disable=import-outside-toplevel
  if config.encoder == "savi":
    from roboshape.train import pretrain
    return pretrain.load_encoder(workdir)
  if config.encoder == "r3m":
    from roboshape.baselines import r3m
    return r3m.load_encoder(config.baselines.r3m, resolution=config.env.resolution)
  if config.encoder == "dino":
    from roboshape.baselines import dino
    return dino.load_encoder(config.baselines.dino, resolution=config.env.resolution)
  raise ValueError(f"unknown encoder {config.encoder!r}")
