"""benchmarks/gpu_scaleup.py on a machine without a GPU: its one line and exit 0, and the `:paper` grid's hours it
projects from step times (runs x steps x seconds a step, per encoder); benchmarks/flops.py's FLOP counts."""
import functools
import importlib
import os
import sys

import pytest

BENCHMARKS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks")


@pytest.fixture(name="scaleup")
def _scaleup(monkeypatch):
  monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))   # whatever its import sets is undone after
  monkeypatch.syspath_prepend(BENCHMARKS)
  return importlib.import_module("gpu_scaleup")


def test_without_a_gpu_it_says_so_in_one_line_and_exits_0(scaleup, monkeypatch, capsys):
  monkeypatch.setattr(sys, "argv", ["gpu_scaleup.py"])
  assert scaleup.main() == 0
  out = capsys.readouterr().out.strip().splitlines()
  assert len(out) == 1 and out[0].startswith("gpu_scaleup: no GPU found") and "stay unmeasured" in out[0]


def test_the_paper_grid_hours_are_runs_times_steps_times_the_step_time(scaleup):
  rows = {r.encoder: r for r in scaleup.grid_rows({"savi": 2.0, "ae": 0.5}, 0.01)}
  savi, ae, r3m = rows["savi"], rows["ae"], rows["r3m"]
  # :paper: one pretraining run and three policy seeds of 100k steps per task, three tasks
  assert (savi.tasks, savi.pretrain_runs, savi.pretrain_steps, savi.bc_runs, savi.bc_steps) == (3, 3, 100000, 9,
                                                                                                100000)
  assert savi.pretrain_s == pytest.approx(3 * 100000 * 2.0) and ae.pretrain_s == pytest.approx(3 * 100000 * 0.5)
  assert savi.bc_s == r3m.bc_s == pytest.approx(9 * 100000 * 0.01)
  assert (r3m.pretrain_runs, r3m.pretrain_s) == (0, 0.0)                  # frozen weights: nothing to pretrain
  assert {e for e, r in rows.items() if r.in_paper_grid} == {"savi", "r3m", "dino"}


def test_step_flops_count_a_matmul_and_a_convolution_as_their_arithmetic(monkeypatch):
  """The FLOPs the benchmarks divide by: 2 m k n for a matmul, 2 x output pixels x kernel area x C_in x C_out for a
  convolution (the counts a GPU's compiled module would miss, its convolutions and matmuls being library calls)."""
  import jax                                         # pylint: disable=import-outside-toplevel
  import jax.numpy as jnp                            # pylint: disable=import-outside-toplevel
  monkeypatch.syspath_prepend(BENCHMARKS)
  flops = importlib.import_module("flops")
  a, b = jnp.zeros((8, 16), jnp.float32), jnp.zeros((16, 4), jnp.float32)
  assert flops.step_flops(jax.jit(jnp.dot), a, b) == 2 * 8 * 16 * 4
  x, w = jnp.zeros((2, 12, 12, 3), jnp.float32), jnp.zeros((5, 5, 3, 7), jnp.float32)   # NHWC, HWIO
  conv = functools.partial(jax.lax.conv_general_dilated, window_strides=(1, 1),
                           dimension_numbers=("NHWC", "HWIO", "NHWC"))
  assert flops.step_flops(jax.jit(functools.partial(conv, padding="VALID")), x, w) == 2 * (2 * 8 * 8) * 25 * 3 * 7
  # SAME pads by 2: a row's 12 outputs see 3, 4, 5 x 8, 4, 3 of the kernel's 5 taps (54), and only those are counted
  assert flops.step_flops(jax.jit(functools.partial(conv, padding="SAME")), x, w) == 2 * (2 * 54 * 54) * 3 * 7

