"""Small Flax building blocks shared by roboshape's models: coordinate grids, position embeddings, MLPs and a
transformer block over a set of tokens."""
from typing import Optional

import flax.linen as nn
import jax.numpy as jnp


def coordinate_grid(height: int, width: int) -> jnp.ndarray:
  """Pixel-centre coordinates of a [height, width] grid -> float32 [H, W, 4] holding (y, x, 1 - y, 1 - x) in [0, 1]."""
  ys = (jnp.arange(height, dtype=jnp.float32) + 0.5) / height
  xs = (jnp.arange(width, dtype=jnp.float32) + 0.5) / width
  y, x = jnp.meshgrid(ys, xs, indexing="ij")
  return jnp.stack([y, x, 1.0 - y, 1.0 - x], axis=-1)


class PositionEmbedding(nn.Module):
  """Adds a learned linear projection of the pixel coordinates to a feature map.

  inputs [..., H, W, C] -> [..., H, W, C]
  """

  @nn.compact
  def __call__(self, inputs: jnp.ndarray) -> jnp.ndarray:
    height, width, channels = inputs.shape[-3:]
    grid = coordinate_grid(height, width)
    return inputs + nn.Dense(channels, name="project")(grid)


class MLP(nn.Module):
  """Dense -> ReLU -> Dense, with an optional LayerNorm in front and an optional residual connection.

  zero_output: the last layer starts at zero (the MLP starts as the zero map, or as the identity when residual).
  inputs [..., C] -> [..., output_size or C]
  """
  hidden_size: int
  output_size: Optional[int] = None
  layernorm: bool = False
  residual: bool = False
  zero_output: bool = False

  @nn.compact
  def __call__(self, inputs: jnp.ndarray) -> jnp.ndarray:
    x = nn.LayerNorm(name="norm")(inputs) if self.layernorm else inputs
    x = nn.relu(nn.Dense(self.hidden_size, name="hidden")(x))
    init = nn.initializers.zeros if self.zero_output else nn.linear.default_kernel_init
    x = nn.Dense(self.output_size or inputs.shape[-1], kernel_init=init, name="output")(x)
    return inputs + x if self.residual else x


class TransformerBlock(nn.Module):
  """A post-norm transformer block over a set: self-attention then an MLP, each residual and layer-normalised.

  Equivariant to permutations of the set (no position information). identity_init: the attention's output
  projection and the MLP's last layer start at zero, so the block starts as LayerNorm(inputs): every token keeps
  its own content instead of being mixed with the others by a random attention.
  inputs [B, N, D] -> [B, N, D]
  """
  num_heads: int
  mlp_size: int
  identity_init: bool = False

  @nn.compact
  def __call__(self, inputs: jnp.ndarray) -> jnp.ndarray:
    width = inputs.shape[-1]
    out_init = nn.initializers.zeros if self.identity_init else nn.linear.default_kernel_init
    attended = nn.MultiHeadDotProductAttention(num_heads=self.num_heads, qkv_features=width, out_kernel_init=out_init,
                                               name="attention")(inputs, inputs)
    x = nn.LayerNorm(name="norm_attention")(inputs + attended)
    x = nn.LayerNorm(name="norm_mlp")(x + MLP(self.mlp_size, width, zero_output=self.identity_init, name="mlp")(x))
    return x
