"""ResNet-18/34/50 in Flax, inference only: BatchNorm uses its running statistics (collection "batch_stats").

The layout is the classic ImageNet ResNet (v1.5: a bottleneck block strides in its 3x3 conv) without the
classifier, so the output is the globally average-pooled feature: 512 wide for ResNet-18/34, 2048 for ResNet-50.
Submodule names follow the torch state_dict (conv1, bn1, layer1_0/conv1, layer1_0/downsample_0, ...) so that
roboshape.baselines.convert maps the official weights without a table.
"""
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

ARCHS = {
    "resnet18": ("basic", (2, 2, 2, 2)),
    "resnet34": ("basic", (3, 4, 6, 3)),
    "resnet50": ("bottleneck", (3, 4, 6, 3)),
}


def _bn(name: str) -> nn.BatchNorm:
  return nn.BatchNorm(use_running_average=True, momentum=0.9, epsilon=1e-5, name=name)


def _conv(features: int, size: int, stride: int, name: str) -> nn.Conv:
  pad = size // 2
  return nn.Conv(features, (size, size), strides=(stride, stride), padding=((pad, pad), (pad, pad)),
                 use_bias=False, name=name)


class BasicBlock(nn.Module):
  """Two 3x3 convs with a residual: [B, H, W, C] -> [B, H/stride, W/stride, features]."""
  features: int
  stride: int = 1
  downsample: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.relu(_bn("bn1")(_conv(self.features, 3, self.stride, "conv1")(x)))
    y = _bn("bn2")(_conv(self.features, 3, 1, "conv2")(y))
    if self.downsample:
      x = _bn("downsample_1")(_conv(self.features, 1, self.stride, "downsample_0")(x))
    return nn.relu(x + y)


class Bottleneck(nn.Module):
  """1x1 -> 3x3 (strided) -> 1x1 x4 with a residual: [B, H, W, C] -> [B, H/stride, W/stride, 4 * features]."""
  features: int
  stride: int = 1
  downsample: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    y = nn.relu(_bn("bn1")(_conv(self.features, 1, 1, "conv1")(x)))
    y = nn.relu(_bn("bn2")(_conv(self.features, 3, self.stride, "conv2")(y)))
    y = _bn("bn3")(_conv(4 * self.features, 1, 1, "conv3")(y))
    if self.downsample:
      x = _bn("downsample_1")(_conv(4 * self.features, 1, self.stride, "downsample_0")(x))
    return nn.relu(x + y)


class ResNet(nn.Module):
  """Normalised images [B, H, W, 3] -> pooled features [B, D] (D = 512, or 2048 for bottleneck blocks)."""
  block: str = "basic"
  stage_sizes: Sequence[int] = (2, 2, 2, 2)

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    x = nn.relu(_bn("bn1")(_conv(64, 7, 2, "conv1")(x)))
    x = nn.max_pool(x, (3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))
    block_cls = BasicBlock if self.block == "basic" else Bottleneck
    expansion = 1 if self.block == "basic" else 4
    in_features = 64
    for stage, num_blocks in enumerate(self.stage_sizes):
      features = 64 * 2 ** stage
      for i in range(num_blocks):
        stride = 2 if stage > 0 and i == 0 else 1
        downsample = i == 0 and (stride != 1 or in_features != features * expansion)
        x = block_cls(features, stride, downsample, name=f"layer{stage + 1}_{i}")(x)
        in_features = features * expansion
    return jnp.mean(x, axis=(1, 2))


def resnet(arch: str) -> ResNet:
  """The ResNet named "resnet18", "resnet34" or "resnet50"."""
  block, stages = ARCHS[arch]
  return ResNet(block=block, stage_sizes=stages)


def output_dim(arch: str) -> int:
  return 2048 if ARCHS[arch][0] == "bottleneck" else 512
