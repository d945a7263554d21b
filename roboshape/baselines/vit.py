"""Vision Transformers ViT-S/16 and ViT-B/16 in Flax, inference only (no dropout, no classifier).

Pre-norm blocks with exact GELU and LayerNorm eps 1e-6; the output is the final-norm token sequence, CLS first.
Position embeddings are learnt for the pretraining resolution (224 -> a 14 x 14 grid) and resized bicubically
for other inputs with the same convention as the original training code (torch's bicubic with a = -0.75, clamped
borders, and a target grid widened by 0.1 cell to dodge rounding). Submodule names follow the torch state_dict
(patch_embed/proj, blocks_0/attn/qkv, ...) so roboshape.baselines.convert maps official weights without a table.
"""
import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

ARCHS = {
    "vits16": dict(embed_dim=384, depth=12, num_heads=6),
    "vitb16": dict(embed_dim=768, depth=12, num_heads=12),
}


def _cubic_weights(t: float, a: float = -0.75):
  """The four bicubic-convolution weights for the taps at offsets -1, 0, 1, 2 of a fractional position t."""
  def near(x):  # |x| <= 1
    return ((a + 2) * x - (a + 3)) * x * x + 1
  def far(x):  # 1 < |x| < 2
    return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
  return (far(t + 1), near(t), near(1 - t), far(2 - t))


@functools.lru_cache(maxsize=None)
def bicubic_matrix(in_size: int, out_size: int, scale: float) -> np.ndarray:
  """[out_size, in_size] matrix of a 1-D bicubic resize with scale factor `scale` (half-pixel centres).

  Matches torch's `interpolate(mode="bicubic", scale_factor=scale, align_corners=False)`: the source position
  of output o is (o + 0.5) / scale - 0.5, and taps beyond the border repeat the edge sample.
  """
  m = np.zeros((out_size, in_size), np.float64)
  for o in range(out_size):
    src = np.float32((o + 0.5) * np.float32(1.0 / scale) - 0.5)
    i0 = math.floor(src)
    for k, w in zip(range(i0 - 1, i0 + 3), _cubic_weights(float(src) - i0)):
      m[o, min(max(k, 0), in_size - 1)] += w
  return m.astype(np.float32)


def resize_pos_embed(pos_embed: jax.Array, grid_h: int, grid_w: int) -> jax.Array:
  """[1, 1 + n*n, D] position embeddings of an n x n grid -> [1, 1 + grid_h*grid_w, D]."""
  n = int(round(math.sqrt(pos_embed.shape[1] - 1)))
  if (grid_h, grid_w) == (n, n):
    return pos_embed
  grid = pos_embed[0, 1:].reshape(n, n, -1)
  rows = jnp.asarray(bicubic_matrix(n, grid_h, (grid_h + 0.1) / n))
  cols = jnp.asarray(bicubic_matrix(n, grid_w, (grid_w + 0.1) / n))
  grid = jnp.einsum("ai,ijd,bj->abd", rows, grid, cols, precision=jax.lax.Precision.HIGHEST)
  return jnp.concatenate([pos_embed[:, :1], grid.reshape(1, grid_h * grid_w, -1)], axis=1)


def _layer_norm(name: str) -> nn.LayerNorm:
  return nn.LayerNorm(epsilon=1e-6, use_fast_variance=False, name=name)


class PatchEmbed(nn.Module):
  """[B, H, W, 3] -> [B, H/p, W/p, D] by a p x p stride-p convolution."""
  embed_dim: int
  patch_size: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    p = self.patch_size
    return nn.Conv(self.embed_dim, (p, p), strides=(p, p), padding="VALID", name="proj")(x)


class Attention(nn.Module):
  """Multi-head self-attention over [B, N, D]."""
  num_heads: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    b, n, d = x.shape
    head_dim = d // self.num_heads
    qkv = nn.Dense(3 * d, name="qkv")(x).reshape(b, n, 3, self.num_heads, head_dim)
    q, k, v = jnp.transpose(qkv, (2, 0, 3, 1, 4))  # [B, heads, N, head_dim] each
    logits = (q @ jnp.swapaxes(k, -1, -2)) * head_dim ** -0.5  # [B, heads, N, N]
    # Softmax with the normalisation after the value product: XLA on CPU then keeps both products as plain
    # batched matmuls instead of fusing them into slow loops with the elementwise work.
    weights = jnp.exp(logits - jnp.max(logits, axis=-1, keepdims=True))
    out = (weights @ v) / jnp.sum(weights, axis=-1, keepdims=True)  # [B, heads, N, head_dim]
    return nn.Dense(d, name="proj")(jnp.swapaxes(out, 1, 2).reshape(b, n, d))


class Mlp(nn.Module):
  """Dense -> exact GELU -> Dense over [B, N, D]."""
  hidden: int

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.gelu(nn.Dense(self.hidden, name="fc1")(x), approximate=False)
    return nn.Dense(x.shape[-1], name="fc2")(y)


class Block(nn.Module):
  """Pre-norm transformer block over [B, N, D]."""
  num_heads: int
  mlp_ratio: float = 4.0

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = x + Attention(self.num_heads, name="attn")(_layer_norm("norm1")(x))
    return x + Mlp(int(x.shape[-1] * self.mlp_ratio), name="mlp")(_layer_norm("norm2")(x))


class VisionTransformer(nn.Module):
  """Normalised images [B, H, W, 3] -> final-norm tokens [B, 1 + (H/p)(W/p), D], the CLS token first."""
  embed_dim: int = 384
  depth: int = 12
  num_heads: int = 6
  patch_size: int = 16
  pretrain_size: int = 224

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    b = x.shape[0]
    x = PatchEmbed(self.embed_dim, self.patch_size, name="patch_embed")(x)
    grid_h, grid_w = x.shape[1:3]
    x = x.reshape(b, grid_h * grid_w, self.embed_dim)
    n = self.pretrain_size // self.patch_size
    init = nn.initializers.normal(0.02)
    cls_token = self.param("cls_token", init, (1, 1, self.embed_dim))
    pos_embed = self.param("pos_embed", init, (1, 1 + n * n, self.embed_dim))
    x = jnp.concatenate([jnp.broadcast_to(cls_token, (b, 1, self.embed_dim)), x], axis=1)
    x = x + resize_pos_embed(pos_embed, grid_h, grid_w)
    for i in range(self.depth):
      x = Block(self.num_heads, name=f"blocks_{i}")(x)
    return _layer_norm("norm")(x)


def vit(arch: str) -> VisionTransformer:
  """The ViT named "vits16" or "vitb16"."""
  return VisionTransformer(**ARCHS[arch])
