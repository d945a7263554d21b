"""A toy encoder, registered by this one module as a new encoder would be (tests/test_encoders.py runs it through the
config check, the stage wiring and the tiny pipeline; no other file names it).

`toy`: a frame becomes 4 tokens, the mean colour of each quadrant of the image, times `toy.scale`; no weights to
load and no pretraining. Its own config section is `toy` (`section()` gives its defaults), whose one range is
declared here and checked by its `check`.
"""
import ml_collections

from roboshape import encoders
from roboshape import ranges

NAME = "toy"
RANGES = (ranges.Number("toy.scale", 0.0, "the factor the quadrant colours are multiplied by", low_ok=False),)


def section() -> ml_collections.ConfigDict:
  """The toy's config section, with its defaults (an experiment config adds it as config.toy)."""
  return ml_collections.ConfigDict(dict(scale=1.0))


def tokens(frames, scale: float):
  """uint8 [B, H, W, 3] (H, W even) -> float32 [B, 4, 3]: the quadrants' mean colours in [0, 1] (top left, top
  right, bottom left, bottom right) times `scale`."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  x = jnp.asarray(frames, jnp.float32) / 255.0
  b, h, w, c = x.shape
  return x.reshape(b, 2, h // 2, 2, w // 2, c).mean(axis=(2, 4)).reshape(b, 4, c) * scale


def _step(params, carry, frames):
  return tokens(frames, params["scale"]), carry


def _build(config, workdir: str):
  del workdir
  from roboshape.models.encoder import FrozenEncoder  # pylint: disable=import-outside-toplevel
  scale = float(config.toy.scale)
  return FrozenEncoder(name=NAME, params={"scale": scale}, step=_step, init_state=lambda batch_size: (),
                       num_tokens=4, token_dim=3, identity=f"toy:quadrants*{scale}")


def check(config) -> None:
  ranges.check(config, RANGES)


KIND = encoders.register(encoders.Kind(
    name=NAME, inputs=("image",), pretrain="", build=_build, title="Toy",
    description="each image quadrant's mean colour (a test encoder)", sections=("toy",), check=check,
    family="global", order=50, tokens=lambda config: "4 x 3"))
