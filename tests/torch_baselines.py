"""Independent torch references for the R3M and DINO baselines, written with torch.nn.functional ops only.

Used by tests/test_baselines.py and benchmarks/baselines_speed.py; nothing here imports roboshape. It builds
random weights in the layout and key names of the official files:

  R3M  model.pt: {"r3m": {"module.convnet.<torch ResNet key>": tensor, "module.lang_rew.*": ...}}
  DINO *_pretrain.pth: {"cls_token", "pos_embed", "patch_embed.proj.*", "blocks.i.*", "norm.*"}

and runs the forward passes the way the original code does (NCHW, BatchNorm in eval mode, bicubic resize of
the position embeddings with a 0.1-cell margin).
"""
import math

import torch
import torch.nn.functional as F

RESNETS = {"resnet18": ("basic", (2, 2, 2, 2)), "resnet34": ("basic", (3, 4, 6, 3)),
           "resnet50": ("bottleneck", (3, 4, 6, 3))}
VITS = {"vits16": (384, 12, 6), "vitb16": (768, 12, 12)}
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


# ----------------------------------------------------------------------------------------------- random weights
def _conv(gen, out_c, in_c, k):
  return torch.randn(out_c, in_c, k, k, generator=gen) * math.sqrt(1.0 / (in_c * k * k))


def _bn(gen, sd, name, c):
  sd[f"{name}.weight"] = 0.5 + torch.rand(c, generator=gen)
  sd[f"{name}.bias"] = 0.1 * torch.randn(c, generator=gen)
  sd[f"{name}.running_mean"] = 0.1 * torch.randn(c, generator=gen)
  sd[f"{name}.running_var"] = 0.5 + torch.rand(c, generator=gen)
  sd[f"{name}.num_batches_tracked"] = torch.tensor(1000)


def resnet_state(arch, seed=0):
  """A random state_dict with torch's ResNet key names (no fc: the R3M convnet's classifier is an identity)."""
  gen = torch.Generator().manual_seed(seed)
  block, stages = RESNETS[arch]
  expansion = 1 if block == "basic" else 4
  sd = {"conv1.weight": _conv(gen, 64, 3, 7)}
  _bn(gen, sd, "bn1", 64)
  in_c = 64
  for s, n in enumerate(stages):
    width = 64 * 2 ** s
    for b in range(n):
      p = f"layer{s + 1}.{b}"
      if block == "basic":
        convs = [(width, in_c, 3), (width, width, 3)]
      else:
        convs = [(width, in_c, 1), (width, width, 3), (width * expansion, width, 1)]
      for j, (o, i, k) in enumerate(convs, 1):
        sd[f"{p}.conv{j}.weight"] = _conv(gen, o, i, k)
        _bn(gen, sd, f"{p}.bn{j}", o)
      if b == 0 and (s > 0 or in_c != width * expansion):
        sd[f"{p}.downsample.0.weight"] = _conv(gen, width * expansion, in_c, 1)
        _bn(gen, sd, f"{p}.downsample.1", width * expansion)
      in_c = width * expansion
  return sd


def r3m_file_payload(arch, seed=0):
  """What the official R3M model.pt holds: a DataParallel state_dict under "r3m", language heads included."""
  sd = {f"module.convnet.{k}": v for k, v in resnet_state(arch, seed).items()}
  gen = torch.Generator().manual_seed(seed + 1)
  sd["module.lang_rew.pred.0.weight"] = torch.randn(1024, 2048 + 768, generator=gen) * 0.01
  sd["module.lang_rew.pred.0.bias"] = torch.zeros(1024)
  return {"r3m": sd, "global_step": 1500000}


def vit_state(arch, seed=0, img_size=224, patch=16):
  """A random state_dict with the DINO ViT key names (the pretrain files hold the backbone only)."""
  gen = torch.Generator().manual_seed(seed)
  d, depth, _ = VITS[arch]
  n = (img_size // patch) ** 2

  def lin(o, i):
    return torch.randn(o, i, generator=gen) * math.sqrt(1.0 / i), 0.05 * torch.randn(o, generator=gen)

  def ln(name):
    sd[f"{name}.weight"] = 1.0 + 0.1 * torch.randn(d, generator=gen)
    sd[f"{name}.bias"] = 0.1 * torch.randn(d, generator=gen)

  sd = {"cls_token": 0.5 * torch.randn(1, 1, d, generator=gen),
        "pos_embed": 0.5 * torch.randn(1, n + 1, d, generator=gen),
        "patch_embed.proj.weight": _conv(gen, d, 3, patch),
        "patch_embed.proj.bias": 0.05 * torch.randn(d, generator=gen)}
  for i in range(depth):
    p = f"blocks.{i}"
    ln(f"{p}.norm1")
    sd[f"{p}.attn.qkv.weight"], sd[f"{p}.attn.qkv.bias"] = lin(3 * d, d)
    sd[f"{p}.attn.proj.weight"], sd[f"{p}.attn.proj.bias"] = lin(d, d)
    ln(f"{p}.norm2")
    sd[f"{p}.mlp.fc1.weight"], sd[f"{p}.mlp.fc1.bias"] = lin(4 * d, d)
    sd[f"{p}.mlp.fc2.weight"], sd[f"{p}.mlp.fc2.bias"] = lin(d, 4 * d)
  ln("norm")
  return sd


# ----------------------------------------------------------------------------------------------- forward passes
def preprocess(frames, size):
  """uint8 [B, H, W, 3] numpy/tensor -> float32 NCHW, resized to size x size (0: as is), ImageNet-normalised."""
  x = torch.as_tensor(frames).permute(0, 3, 1, 2).float() / 255.0
  if size and tuple(x.shape[2:]) != (size, size):
    x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=x.shape[2] > size)
  return (x - MEAN) / STD


def _bn_eval(x, sd, name):
  return F.batch_norm(x, sd[f"{name}.running_mean"], sd[f"{name}.running_var"], sd[f"{name}.weight"],
                      sd[f"{name}.bias"], training=False, eps=1e-5)


def resnet_forward(sd, x):
  """torch ResNet (weights `sd`, architecture read off its keys) on normalised NCHW x -> pooled [B, D]."""
  x = F.relu(_bn_eval(F.conv2d(x, sd["conv1.weight"], stride=2, padding=3), sd, "bn1"))
  x = F.max_pool2d(x, 3, 2, 1)
  bottleneck = "layer1.0.conv3.weight" in sd
  for s in range(1, 5):
    b = 0
    while f"layer{s}.{b}.conv1.weight" in sd:
      p = f"layer{s}.{b}"
      stride = 2 if s > 1 and b == 0 else 1
      if bottleneck:
        y = F.relu(_bn_eval(F.conv2d(x, sd[f"{p}.conv1.weight"]), sd, f"{p}.bn1"))
        y = F.relu(_bn_eval(F.conv2d(y, sd[f"{p}.conv2.weight"], stride=stride, padding=1), sd, f"{p}.bn2"))
        y = _bn_eval(F.conv2d(y, sd[f"{p}.conv3.weight"]), sd, f"{p}.bn3")
      else:
        y = F.relu(_bn_eval(F.conv2d(x, sd[f"{p}.conv1.weight"], stride=stride, padding=1), sd, f"{p}.bn1"))
        y = _bn_eval(F.conv2d(y, sd[f"{p}.conv2.weight"], padding=1), sd, f"{p}.bn2")
      if f"{p}.downsample.0.weight" in sd:
        x = _bn_eval(F.conv2d(x, sd[f"{p}.downsample.0.weight"], stride=stride), sd, f"{p}.downsample.1")
      x = F.relu(x + y)
      b += 1
  return x.mean(dim=(2, 3))


def vit_forward(sd, x, num_heads, patch=16):
  """torch DINO ViT on normalised NCHW x -> final-norm tokens [B, 1 + patches, D] (CLS first)."""
  b, _, h, w = x.shape
  d = sd["cls_token"].shape[-1]
  x = F.conv2d(x, sd["patch_embed.proj.weight"], sd["patch_embed.proj.bias"], stride=patch)
  x = x.flatten(2).transpose(1, 2)
  pos = sd["pos_embed"]
  n_pos = pos.shape[1] - 1
  if x.shape[1] != n_pos or h != w:
    n = int(math.sqrt(n_pos))
    grid = pos[:, 1:].reshape(1, n, n, d).permute(0, 3, 1, 2)
    grid = F.interpolate(grid, scale_factor=((h // patch + 0.1) / n, (w // patch + 0.1) / n), mode="bicubic")
    pos = torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, -1, d)], dim=1)
  x = torch.cat([sd["cls_token"].expand(b, -1, -1), x], dim=1) + pos
  i = 0
  while f"blocks.{i}.norm1.weight" in sd:
    p = f"blocks.{i}"
    y = F.layer_norm(x, (d,), sd[f"{p}.norm1.weight"], sd[f"{p}.norm1.bias"], eps=1e-6)
    qkv = F.linear(y, sd[f"{p}.attn.qkv.weight"], sd[f"{p}.attn.qkv.bias"])
    q, k, v = qkv.reshape(b, -1, 3, num_heads, d // num_heads).permute(2, 0, 3, 1, 4)
    attn = ((q @ k.transpose(-2, -1)) * (d // num_heads) ** -0.5).softmax(dim=-1)
    y = (attn @ v).transpose(1, 2).reshape(b, -1, d)
    x = x + F.linear(y, sd[f"{p}.attn.proj.weight"], sd[f"{p}.attn.proj.bias"])
    y = F.layer_norm(x, (d,), sd[f"{p}.norm2.weight"], sd[f"{p}.norm2.bias"], eps=1e-6)
    y = F.linear(F.gelu(F.linear(y, sd[f"{p}.mlp.fc1.weight"], sd[f"{p}.mlp.fc1.bias"])),
                 sd[f"{p}.mlp.fc2.weight"], sd[f"{p}.mlp.fc2.bias"])
    x = x + y
    i += 1
  return F.layer_norm(x, (d,), sd["norm.weight"], sd["norm.bias"], eps=1e-6)


@torch.no_grad()
def r3m_features(sd, frames, size=224):
  """R3M reference: uint8 [B, H, W, 3] -> [B, D]."""
  return resnet_forward(sd, preprocess(frames, size))


@torch.no_grad()
def dino_tokens(sd, frames, num_heads, size=224):
  """DINO reference: uint8 [B, H, W, 3] -> [B, 1 + patches, D]."""
  return vit_forward(sd, preprocess(frames, size), num_heads)
