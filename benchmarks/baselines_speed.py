"""Feature-extraction speed of the R3M and DINO encoders: roboshape's JAX vs the torch reference, same run.

  JAX_PLATFORMS=cpu .venv/bin/python benchmarks/baselines_speed.py [--archs=resnet18,vits16] [--reps=3] [--noynn_dots]

For every architecture it writes random weights into a file of the official layout, loads it with
roboshape.baselines (r3m / dino `load_encoder`), and times batches of 32 frames at the dataset resolution
(64 x 64, resized to 224 inside as the original projects do) through the jitted JAX step and through the
functional torch reference of tests/torch_baselines.py (torch.no_grad, torch's own thread pool), interleaved, best of --reps. It prints
frames/s of each, their ratio (bar: JAX >= 0.8 x torch) and the largest absolute difference of the outputs.
"""
import os
import sys
import tempfile
import time

from absl import app
from absl import flags
import jax
import ml_collections
import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [ROOT, os.path.join(ROOT, "tests")]
from roboshape.baselines import dino  # pylint: disable=g-import-not-at-top,wrong-import-position
from roboshape.baselines import r3m  # pylint: disable=g-import-not-at-top,wrong-import-position
import torch_baselines as ref  # pylint: disable=g-import-not-at-top,wrong-import-position

_ARCHS = flags.DEFINE_list("archs", ["resnet18", "resnet34", "resnet50", "vits16", "vitb16"], "architectures")
_BATCH = flags.DEFINE_integer("batch", 32, "frames per batch")
_RESOLUTION = flags.DEFINE_integer("resolution", 64, "side of the frames (the dataset's resolution)")
_REPS = flags.DEFINE_integer("reps", 3, "timed batches per framework, interleaved, after one warm-up batch; the best counts")
_YNN = flags.DEFINE_bool("ynn_dots", True, "keep XLA's default YNNPACK fusions for dots on CPU; --noynn_dots sets "
                         "XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type= (Eigen dots) for this process")


def _time(fns, reps):
  """Best-of-`reps` seconds per call of each function, their calls interleaved so both see the same load."""
  for fn in fns:
    fn()  # warm-up (and compilation for JAX)
  best = [float("inf")] * len(fns)
  for _ in range(reps):
    for i, fn in enumerate(fns):
      start = time.perf_counter()
      fn()
      best[i] = min(best[i], time.perf_counter() - start)
  return best


def _bench(arch, frames, workdir, reps):
  """(jax frames/s, torch frames/s, max abs error) of one architecture."""
  if arch in ref.RESNETS:
    path = os.path.join(workdir, f"{arch}.pt")
    torch.save(ref.r3m_file_payload(arch), path)
    enc = r3m.load_encoder(ml_collections.ConfigDict(dict(arch=arch, path=path, input_size=224)),
                           frames.shape[1])
    state = ref.resnet_state(arch)
    torch_fn = lambda: ref.r3m_features(state, frames)[:, None]
  else:
    path = os.path.join(workdir, f"{arch}.pth")
    torch.save(ref.vit_state(arch), path)
    enc = dino.load_encoder(ml_collections.ConfigDict(dict(arch=arch, path=path, input_size=224,
                                                           patch_tokens=False)), frames.shape[1])
    state = ref.vit_state(arch)
    torch_fn = lambda: ref.dino_tokens(state, frames, ref.VITS[arch][2])[:, :1]
  step = jax.jit(lambda params, x: enc.step(params, (), x)[0])
  frames_jax = jax.device_put(frames)
  jax_fn = lambda: step(enc.params, frames_jax).block_until_ready()
  error = float(np.abs(np.asarray(jax_fn()) - torch_fn().numpy()).max())
  t_jax, t_torch = _time([jax_fn, torch_fn], reps)
  n = frames.shape[0]
  return n / t_jax, n / t_torch, error


def main(argv):
  del argv
  if not _YNN.value:  # read when the XLA backend starts, i.e. at the first computation below
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_experimental_ynn_fusion_type=").strip()
  frames = np.random.default_rng(0).integers(0, 256, (_BATCH.value, _RESOLUTION.value, _RESOLUTION.value, 3),
                                             dtype=np.uint8)
  print(f"batch {_BATCH.value} frames of {_RESOLUTION.value}x{_RESOLUTION.value} (resized to 224 inside); "
        f"jax {jax.__version__} on {jax.devices()[0].platform}, torch {torch.__version__} with "
        f"{torch.get_num_threads()} threads, {os.cpu_count()} CPUs, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
  print(f"{'arch':<10}{'jax frames/s':>14}{'torch frames/s':>16}{'jax/torch':>11}{'max abs err':>13}")
  with tempfile.TemporaryDirectory() as workdir:
    for arch in _ARCHS.value:
      jax_fps, torch_fps, error = _bench(arch, frames, workdir, _REPS.value)
      print(f"{arch:<10}{jax_fps:>14.1f}{torch_fps:>16.1f}{jax_fps / torch_fps:>10.2f}x{error:>13.2e}", flush=True)


if __name__ == "__main__":
  app.run(main)
