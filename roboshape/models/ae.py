"""AE: a holistic frame autoencoder built from SAVi's own parts, the in-domain baseline without objects.

Per frame, independently (no slots, no recurrence): SAVi's CNN encoder (savi.CNNEncoder, with input pooling) gives
a feature map; it is average-pooled to the decoder's broadcast grid (g x g, 8 x 8 in every variant), flattened
and mapped by an MLP (LayerNorm, Dense, ReLU, Dense) to one latent vector of `latent_size`. SAVi's spatial-broadcast
decoder (savi.SpatialBroadcastDecoder, with its position embedding and depth output) decodes that latent as a single
"slot" with per-pixel RGB (rgb="spatial"): its mask, a softmax over one slot, is 1 everywhere, so the reconstruction
is the decoder's RGB. Its sizes are the config's ae section, which defaults to SAVi's.

  model = model_from_config(config)       # or build_model(config.ae, latent_size, resolution, depth)
  out = model.apply({"params": params}, video)          # video float [B, T, H, W, 3] in [0, 1]
  out["latent"] [B, T, D], out["recon"] [B, T, h, w, 3] (and out["depth"] [B, T, h, w]), h = H / ae.pool

  latent = model.apply({"params": params}, frames, method=AE.encode)  # frames [B, H, W, 3] -> [B, D]
  latents, () = frozen_step(model, params, (), frames_uint8)           # the frozen encoder's step: [B, 1, D]

Pooling the features to the decoder's grid before flattening keeps their layout at the resolution the decoder
draws from, and keeps the flattening layer g * g * F x D (F the encoder's output width) whatever the frame size.
"""
import math
from typing import Dict, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from roboshape.errors import UserError
from roboshape.models import layers
from roboshape.models import savi


def feature_side(resolution: int, pool: int, strides: Sequence[int]) -> int:
  """The side of the CNN encoder's feature map for square frames of `resolution` pooled by `pool` ("SAME" convs)."""
  side = resolution // pool
  for stride in strides:
    side = -(-side // stride)
  return side


class AE(nn.Module):
  """Frame autoencoder: SAVi's CNN encoder -> pooled to grid_size x grid_size -> MLP -> latent -> SAVi's decoder.

  Field names and meanings follow savi.SAVi's (no defaults: `build_model` sets them all from a config); latent_size
  is D.
  """
  latent_size: int
  encoder_features: Sequence[int]
  encoder_kernel_size: int
  encoder_strides: Sequence[int]
  encoder_mlp_size: int
  feature_size: int
  decoder_grid_size: int
  decoder_features: Sequence[int]
  decoder_kernel_size: int
  decoder_strides: Sequence[int]
  decoder_upsampling: str
  decoder_position: str
  decoder_depth: bool
  input_pool: int

  def setup(self):
    self.encoder = savi.CNNEncoder(self.encoder_features, self.encoder_kernel_size, self.encoder_strides,
                                   self.encoder_mlp_size, self.feature_size)
    self.to_latent = layers.MLP(self.latent_size, self.latent_size, layernorm=True)
    self.decoder = savi.SpatialBroadcastDecoder(self.decoder_grid_size, self.decoder_features,
                                                self.decoder_kernel_size, self.decoder_strides,
                                                self.decoder_upsampling, rgb="spatial",
                                                position=self.decoder_position, depth=self.decoder_depth)

  def encode(self, frames: jnp.ndarray) -> jnp.ndarray:
    """frames [B, H, W, 3] in [0, 1] -> latents [B, D]."""
    features = self.encoder(savi.pool_frames(frames, self.input_pool))           # [B, N, F]
    batch, num, width = features.shape
    side = math.isqrt(num)
    x = features.reshape(batch, side, side, width)
    factor = side // self.decoder_grid_size
    if factor > 1:
      x = nn.avg_pool(x, (factor, factor), strides=(factor, factor))             # [B, g, g, F]
    return self.to_latent(x.reshape(batch, -1))

  def decode(self, latents: jnp.ndarray) -> Dict[str, jnp.ndarray]:
    """latents [B, D] -> dict(recon [B, h, w, 3]) (and depth [B, h, w] with decoder_depth)."""
    out = self.decoder(latents[:, None, :])                                     # one slot
    return {k: out[k] for k in ("recon", "depth") if k in out}

  def __call__(self, video: jnp.ndarray) -> Dict[str, jnp.ndarray]:
    """video [B, T, H, W, 3] in [0, 1] -> dict(latent [B, T, D], recon [B, T, h, w, 3]) (and depth [B, T, h, w]),
    every frame encoded and decoded on its own."""
    batch, length = video.shape[:2]
    latents = self.encode(video.reshape(batch * length, *video.shape[2:]))
    out = {"latent": latents, **self.decode(latents)}
    return {k: v.reshape(batch, length, *v.shape[1:]) for k, v in out.items()}


def latent_size(config) -> int:
  """D: config.ae.latent_size, or config.savi.slot_size when it is 0 (a token as wide as SAVi's slots)."""
  return int(config.ae.latent_size) or int(config.savi.slot_size)


def frozen_step(model: AE, params, carry, frames: jax.Array):
  """The FrozenEncoder step: (params, (), frames uint8 [B, H, W, 3]) -> (latents [B, 1, D], ()); no memory."""
  latents = model.apply({"params": params}, savi.to_float(frames), method=AE.encode)
  return latents[:, None, :], carry


def check_config(ae_config, resolution: int) -> None:
  """Raises UserError, "ae.<field>=<value>: use ...", unless a `config.ae` section builds an AE for square frames of
  `resolution` pixels a side: savi.check_frames, and encoder features that pool evenly to the decoder's grid. (Its
  ranges are declared with the encoder, roboshape/encoders/ae.py.)"""
  c = ae_config
  savi.check_frames(c, "ae", resolution)
  side = feature_side(resolution, savi.input_pool(c), c.encoder.strides)
  grid = savi.decoder_grid_size(c, resolution)
  if side > grid and side % grid:
    raise UserError(f"the AE pools its {side}x{side} encoder features to the decoder's {grid}x{grid} grid, which "
                    "needs a multiple of it: change ae.encoder.strides or ae.decoder.strides.")


def build_model(ae_config, latent_size: int,  # pylint: disable=redefined-outer-name
                resolution: int, depth: bool = False) -> AE:
  """The AE a `config.ae` section describes (its pool, encoder and decoder; see configs/common.py:ae_config), with
  a latent of `latent_size`, for square frames of `resolution` pixels a side, with a depth output when `depth`."""
  c = ae_config
  return AE(
      latent_size=int(latent_size),
      encoder_features=tuple(c.encoder.features), encoder_kernel_size=int(c.encoder.kernel_size),
      encoder_strides=tuple(c.encoder.strides), encoder_mlp_size=int(c.encoder.mlp_size),
      feature_size=int(c.encoder.output_size),
      decoder_grid_size=savi.decoder_grid_size(c, resolution), decoder_features=tuple(c.decoder.features),
      decoder_kernel_size=int(c.decoder.kernel_size), decoder_strides=tuple(c.decoder.strides),
      decoder_upsampling=str(c.decoder.upsampling), decoder_position=str(c.decoder.position),
      decoder_depth=bool(depth), input_pool=savi.input_pool(c))


def model_from_config(config) -> AE:
  """The AE of a run's config: its ae section and `latent_size`, for frames of env.resolution, with a depth output
  when the pretraining weights depth (savi.depth_weight)."""
  return build_model(config.ae, latent_size(config), int(config.env.resolution), savi.depth_weight(config) > 0)
