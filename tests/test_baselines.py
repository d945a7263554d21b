"""R3M and DINO baselines: official-layout checkpoints -> Flax, parity with an independent torch forward.

Random weights are written into files with the official layout and key names (tests/torch_baselines.py); the
Flax encoders loaded from them must match a torch.nn.functional forward of the same weights to 1e-4 (float32).
ResNet-18 and ViT-S/16 are checked through the whole encoder (uint8 frames, resize, normalisation) with the
network at 224 (64 x 64 frames resized, as the originals do) and at the frames' own 64 x 64 (ViT-S then runs its
resized position embeddings). ResNet-50 (bottleneck blocks) takes a cheaper path: one 64 x 64 frame, network at
64 x 64. ResNet-34 and ViT-B/16 share the code of ResNet-18 and ViT-S/16; their keys and shapes are checked here,
their outputs by the benchmark (benchmarks/baselines_speed.py prints every architecture's parity error at 224 on
batches of 32).
"""
import os

import jax
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from configs import common
from roboshape.baselines import convert
from roboshape.baselines import dino
from roboshape.baselines import r3m
from roboshape.baselines import resnet
from roboshape.baselines import vit
from roboshape.errors import UserError
import torch_baselines as ref

TOL = 1e-4


def _cfg(arch, **kw):
  """A baseline's config section: configs/common.py's defaults of the network `arch` names, with `kw` set."""
  section = common.baseline_config("small")["r3m" if arch.startswith("resnet") else "dino"]
  section.update(dict(arch=arch, **kw))
  return section


def _frames(n, side=64, seed=0):
  return np.random.default_rng(seed).integers(0, 256, (n, side, side, 3), dtype=np.uint8)


def _run(enc, frames):
  return np.asarray(jax.jit(lambda p, x: enc.step(p, enc.init_state(x.shape[0]), x)[0])(enc.params, frames))


@pytest.fixture(scope="module")
def states():
  """Random official-layout state_dicts, built once per architecture (ViT-B/16 alone has 86M weights)."""
  cache = {}
  def get(arch):
    if arch not in cache:
      cache[arch] = ref.resnet_state(arch) if arch in ref.RESNETS else ref.vit_state(arch)
    return cache[arch]
  return get


@pytest.fixture(scope="module")
def files(tmp_path_factory):
  d = tmp_path_factory.mktemp("weights")
  paths = {"resnet18": str(d / "r3m_18.pt"), "vits16": str(d / "dino_vits16.pth"),
           "resnet18_b": str(d / "r3m_18_b.pt")}
  torch.save(ref.r3m_file_payload("resnet18"), paths["resnet18"])
  torch.save(ref.r3m_file_payload("resnet18", seed=5), paths["resnet18_b"])
  torch.save(ref.vit_state("vits16"), paths["vits16"])
  return paths


@pytest.fixture(scope="module")
def r3m18(files):
  return {size: r3m.load_encoder(_cfg(arch="resnet18", path=files["resnet18"], input_size=size), 64)
          for size in (224, 0)}


@pytest.fixture(scope="module")
def dino_s(files):
  return {size: dino.load_encoder(_cfg(arch="vits16", path=files["vits16"], input_size=size, patch_tokens=True),
                                  64) for size in (224, 0)}


# ------------------------------------------------------------------------------------------------- parity
@pytest.mark.parametrize("size", [224, 0])
def test_r3m_resnet18_matches_torch(r3m18, size):
  enc = r3m18[size]
  frames = _frames(2)
  got = _run(enc, frames)
  want = ref.r3m_features(ref.resnet_state("resnet18"), frames, size).numpy()
  assert got.shape == (2, 1, 512) and (enc.num_tokens, enc.token_dim) == (1, 512)
  assert np.abs(want).max() > 1.0  # not a trivially small output
  np.testing.assert_allclose(got[:, 0], want, rtol=0, atol=TOL)


@pytest.mark.parametrize("size", [224, 0])
def test_dino_vits16_matches_torch_with_patch_tokens(dino_s, size):
  enc = dino_s[size]
  frames = _frames(1, seed=1)
  got = _run(enc, frames)
  want = ref.dino_tokens(ref.vit_state("vits16"), frames, num_heads=6, size=size).numpy()
  patches = (size or 64) // 16
  assert got.shape == (1, 1 + patches ** 2, 384) == want.shape and enc.num_tokens == 1 + patches ** 2
  np.testing.assert_allclose(got, want, rtol=0, atol=TOL)


# ResNet-34 and ViT-B/16 run the same module code as ResNet-18 and ViT-S/16 with other sizes (their keys and
# shapes are checked below); ResNet-50's bottleneck blocks are code of their own, so it gets a parity check here.
@pytest.mark.parametrize("arch", ["resnet50"])
def test_bigger_architectures_match_torch_on_one_small_frame(arch, states, tmp_path):
  frames = _frames(1, seed=2)
  path = str(tmp_path / "weights.pt")
  if arch in ref.RESNETS:
    torch.save({"r3m": {f"module.convnet.{k}": v for k, v in states(arch).items()}}, path)
    got = _run(r3m.load_encoder(_cfg(arch=arch, path=path, input_size=0), 64), frames)[:, 0]
    want = ref.r3m_features(states(arch), frames, 0).numpy()
  else:
    torch.save(states(arch), path)
    got = _run(dino.load_encoder(_cfg(arch=arch, path=path, input_size=0, patch_tokens=True), 64), frames)
    want = ref.dino_tokens(states(arch), frames, num_heads=12, size=0).numpy()
  assert got.shape == want.shape
  np.testing.assert_allclose(got, want, rtol=0, atol=TOL)


@pytest.mark.parametrize("grid", [4, 8, 20])
def test_bicubic_position_resize_matches_torch_interpolate(grid):
  x = torch.randn(1, 5, 14, 14, generator=torch.Generator().manual_seed(grid))
  want = F.interpolate(x, scale_factor=((grid + 0.1) / 14,) * 2, mode="bicubic")
  m = vit.bicubic_matrix(14, grid, (grid + 0.1) / 14)
  got = np.einsum("ai,cij,bj->cab", m, x[0].numpy(), m)
  assert want.shape[-2:] == (grid, grid)
  np.testing.assert_allclose(got, want[0].numpy(), rtol=0, atol=1e-5)


@pytest.mark.parametrize("arch", ["resnet18", "resnet34", "resnet50", "vits16", "vitb16"])
def test_flax_modules_expect_exactly_the_official_keys_and_shapes(arch, states):
  model, side = (resnet.resnet(arch), 64) if arch in resnet.ARCHS else (vit.vit(arch), 224)
  official = states(arch)
  template = jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct((1, side, side, 3), np.float32))
  official = {k: tuple(v.shape) for k, v in official.items() if not k.endswith("num_batches_tracked")}
  assert convert.expected_torch_shapes(template) == official


# ------------------------------------------------------------------------------------------------- interface
def test_encode_episode_is_the_step_frame_by_frame(r3m18):
  enc = r3m18[0]
  frames = _frames(2, seed=3)
  episode = np.asarray(enc.encode_episode(frames))
  assert episode.shape == (2, 1, 512)
  np.testing.assert_allclose(episode, _run(enc, frames), rtol=0, atol=1e-5)


def test_identity_follows_the_weights_and_the_input_size(files, r3m18):
  again = r3m.load_encoder(_cfg(arch="resnet18", path=files["resnet18"], input_size=224), 64)
  other = r3m.load_encoder(_cfg(arch="resnet18", path=files["resnet18_b"], input_size=224), 64)
  assert again.identity == r3m18[224].identity
  assert len({r3m18[224].identity, r3m18[0].identity, other.identity}) == 3
  assert files["resnet18"] in again.identity and "resnet18" in again.identity


def test_dino_cls_only_by_default(files, dino_s):
  enc = dino.load_encoder(_cfg(arch="vits16", path=files["vits16"]), 64)
  assert (enc.name, enc.num_tokens, enc.token_dim) == ("dino", 1, 384)
  assert enc.identity != dino_s[224].identity


# ------------------------------------------------------------------------------------------------- errors
def test_missing_file_names_the_default_path_and_the_download_page(tmp_path, monkeypatch):
  monkeypatch.setenv("HOME", str(tmp_path))
  with pytest.raises(UserError) as e:
    r3m.load_encoder(_cfg(arch="resnet50", path=""), 64)
  message = str(e.value)
  assert os.path.join(str(tmp_path), ".r3m", "r3m_50", "model.pt") in message
  assert "github.com/facebookresearch/r3m" in message and "\n" not in message
  monkeypatch.setenv("TORCH_HOME", str(tmp_path / "th"))
  with pytest.raises(UserError) as e:
    dino.load_encoder(_cfg(arch="vitb16", path=""), 64)
  message = str(e.value)
  assert os.path.join(str(tmp_path), "th", "hub", "checkpoints", "dino_vitbase16_pretrain.pth") in message
  assert "https://dl.fbaipublicfiles.com/dino/dino_vitbase16_pretrain/dino_vitbase16_pretrain.pth" in message
  assert "\n" not in message


def test_wrong_model_files_are_refused_with_the_mismatching_keys(files, tmp_path):
  with pytest.raises(UserError, match=r"missing: .*layer1\.0\.conv3\.weight"):
    r3m.load_encoder(_cfg(arch="resnet50", path=files["resnet18"]), 64)
  with pytest.raises(UserError, match=r"another shape: .*qkv\.weight \(1152, 384\) \(expected \(2304, 768\)\)"):
    dino.load_encoder(_cfg(arch="vitb16", path=files["vits16"]), 64)
  with pytest.raises(UserError, match=r"missing: .*blocks\.0\.attn\.qkv\.bias"):
    dino.load_encoder(_cfg(arch="vits16", path=files["resnet18"]), 64)
  with pytest.raises(UserError, match="no 'r3m' entry"):
    r3m.load_encoder(_cfg(arch="resnet18", path=files["vits16"]), 64)
  garbage = tmp_path / "model.pt"
  garbage.write_bytes(b"not a checkpoint")
  with pytest.raises(UserError, match="cannot read"):
    r3m.load_encoder(_cfg(arch="resnet18", path=str(garbage)), 64)
  with pytest.raises(UserError, match="unknown R3M arch"):
    r3m.load_encoder(_cfg(arch="resnet101", path=files["resnet18"]), 64)
