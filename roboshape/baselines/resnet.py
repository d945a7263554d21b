"""ResNet-18/34/50 in Flax, inference only: BatchNorm uses its running statistics (collection "batch_stats").

The layout is the classic ImageNet ResNet (v1.5: a bottleneck block strides in its 3x3 conv) without the
classifier, so the output is the globally average-pooled feature: 512 wide for ResNet-18/34, 2048 for ResNet-50.
Submodule names follow the torch state_dict (conv1, bn1, layer1_0/conv1, layer1_0/downsample_0, ...) so that
roboshape.baselines.convert maps the official weights without a table.

For speed, `fold_batchnorm` folds every inference BatchNorm into the kernel and a bias of the conv before it
(done once, at load time, in float64); the module built with `folded=True` then runs those biased convs and has
no BatchNorm at all. Its outputs equal the unfolded module's up to float32 rounding.
"""
from typing import Any, Dict, Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

ARCHS = {
    "resnet18": ("basic", (2, 2, 2, 2)),
    "resnet34": ("basic", (3, 4, 6, 3)),
    "resnet50": ("bottleneck", (3, 4, 6, 3)),
}
_BN_EPSILON = 1e-5


class Conv(nn.Module):
  """Square conv with symmetric padding size // 2 (torch's `padding=size // 2`), NHWC input, HWIO kernel.

  A 1 x 1 conv runs as a matrix product over the (strided) pixels, which XLA's CPU backend does much faster
  than its generic convolution; the sums are the same. With `defer_bias` the bias is declared but not added:
  the caller adds `variables["params"]["bias"]` itself.
  """
  features: int
  size: int
  stride: int = 1
  use_bias: bool = False
  defer_bias: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (self.size, self.size, x.shape[-1], self.features), jnp.float32)
    if self.size == 1:
      y = jnp.dot(x[:, ::self.stride, ::self.stride, :], kernel[0, 0])
    else:
      pad = self.size // 2
      y = jax.lax.conv_general_dilated(x, kernel, (self.stride, self.stride), ((pad, pad), (pad, pad)),
                                       dimension_numbers=("NHWC", "HWIO", "NHWC"))
    if self.use_bias:
      bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
      if not self.defer_bias:
        y = y + bias
    return y


def _conv_bn(parent: nn.Module, x: jax.Array, features: int, size: int, stride: int, conv_name: str,
             bn_name: str) -> jax.Array:
  """Conv (+ inference BatchNorm unless `parent.folded`) with submodules named `conv_name`, `bn_name` in `parent`."""
  y = Conv(features, size, stride, use_bias=parent.folded, name=conv_name)(x)
  if parent.folded:
    return y
  return nn.BatchNorm(use_running_average=True, momentum=0.9, epsilon=_BN_EPSILON, name=bn_name)(y)


class BasicBlock(nn.Module):
  """Two 3x3 convs with a residual: [B, H, W, C] -> [B, H/stride, W/stride, features]."""
  features: int
  stride: int = 1
  downsample: bool = False
  folded: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.relu(_conv_bn(self, x, self.features, 3, self.stride, "conv1", "bn1"))
    y = _conv_bn(self, y, self.features, 3, 1, "conv2", "bn2")
    if self.downsample:
      x = _conv_bn(self, x, self.features, 1, self.stride, "downsample_0", "downsample_1")
    return nn.relu(x + y)


class Bottleneck(nn.Module):
  """1x1 -> 3x3 (strided) -> 1x1 x4 with a residual: [B, H, W, C] -> [B, H/stride, W/stride, 4 * features]."""
  features: int
  stride: int = 1
  downsample: bool = False
  folded: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.relu(_conv_bn(self, x, self.features, 1, 1, "conv1", "bn1"))
    y = nn.relu(_conv_bn(self, y, self.features, 3, self.stride, "conv2", "bn2"))
    y = _conv_bn(self, y, 4 * self.features, 1, 1, "conv3", "bn3")
    if self.downsample:
      x = _conv_bn(self, x, 4 * self.features, 1, self.stride, "downsample_0", "downsample_1")
    return nn.relu(x + y)


class ResNet(nn.Module):
  """Normalised images [B, H, W, 3] -> pooled features [B, D] (D = 512, or 2048 for bottleneck blocks).

  With `folded`, every BatchNorm is gone and its conv has a bias: the variables are `fold_batchnorm` of the
  official ones.
  """
  block: str = "basic"
  stage_sizes: Sequence[int] = (2, 2, 2, 2)
  folded: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    if self.folded:
      # x -> relu(x + bias) is non-decreasing in x, so it commutes with the max pool: pooling first gives the same
      # numbers and spares a pass over the largest activation of the network.
      stem = Conv(64, 7, 2, use_bias=True, defer_bias=True, name="conv1")
      x = stem(x)
      x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
      x = nn.relu(x + stem.variables["params"]["bias"])
    else:
      x = nn.relu(_conv_bn(self, x, 64, 7, 2, "conv1", "bn1"))
      x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
    block_cls = BasicBlock if self.block == "basic" else Bottleneck
    expansion = 1 if self.block == "basic" else 4
    in_features = 64
    for stage, num_blocks in enumerate(self.stage_sizes):
      features = 64 * 2 ** stage
      for i in range(num_blocks):
        stride = 2 if stage > 0 and i == 0 else 1
        downsample = i == 0 and (stride != 1 or in_features != features * expansion)
        x = block_cls(features, stride, downsample, self.folded, name=f"layer{stage + 1}_{i}")(x)
        in_features = features * expansion
    return jnp.mean(x, axis=(1, 2))


def resnet(arch: str, folded: bool = False) -> ResNet:
  """The ResNet named "resnet18", "resnet34" or "resnet50" (BatchNorms folded into the convs if `folded`)."""
  block, stages = ARCHS[arch]
  return ResNet(block=block, stage_sizes=stages, folded=folded)


def output_dim(arch: str) -> int:
  return 2048 if ARCHS[arch][0] == "bottleneck" else 512


def _fold_tree(params: Mapping[str, Any], stats: Mapping[str, Any]) -> Dict[str, Any]:
  """One module level of `fold_batchnorm`: convs named like their BatchNorm's pair take its affine map."""
  out = {}
  for name, value in params.items():
    if "kernel" in value:  # a conv; its BatchNorm is the sibling conv<i> -> bn<i>, downsample_0 -> downsample_1
      bn = "downsample_1" if name == "downsample_0" else "bn" + name[len("conv"):]
      kernel = np.asarray(value["kernel"], np.float64)
      mean = np.asarray(stats[bn]["mean"], np.float64)
      var = np.asarray(stats[bn]["var"], np.float64)
      scale = np.asarray(params[bn]["scale"], np.float64) / np.sqrt(var + _BN_EPSILON)
      bias = np.asarray(params[bn]["bias"], np.float64) - mean * scale
      out[name] = {"kernel": (kernel * scale).astype(np.float32), "bias": bias.astype(np.float32)}
    elif "scale" not in value:  # a block
      out[name] = _fold_tree(value, stats[name])
  return out


def fold_batchnorm(variables: Mapping[str, Any]) -> Dict[str, Any]:
  """Variables {"params", "batch_stats"} of `resnet(arch)` -> the variables of `resnet(arch, folded=True)`.

  Each inference BatchNorm y = (x - mean) / sqrt(var + eps) * scale + bias of a conv's output becomes part of
  that conv: kernel * s and bias - mean * s with s = scale / sqrt(var + eps), computed in float64.
  """
  return {"params": jax.tree.map(jnp.asarray, _fold_tree(variables["params"], variables["batch_stats"]))}
