"""What the benchmarks measure FLOP rates with: a compiled function's FLOPs and the machine's dense-matmul FLOP/s."""
import time

import jax
import jax.numpy as jnp
import numpy as np


def step_flops(jitted, *args) -> float:
  """FLOPs of one call `jitted(*args)` (a jax.jit function with no static arguments), from XLA's cost analysis of the
  step lowered for the CPU from the arguments' shapes, before any backend optimises it: every convolution and matmul
  as written, whatever device `args` are on. A compiled module's count is the same on a CPU but not on a GPU, whose
  backend turns convolutions and matmuls into cuDNN and cuBLAS calls that XLA's cost analysis counts as nothing (and
  a GPU's lowered module has no cost analysis through JAX's CUDA plugin)."""
  cpu = jax.sharding.SingleDeviceSharding(jax.devices("cpu")[0])
  shapes = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(np.shape(x), x.dtype, sharding=cpu), args)
  function = getattr(jitted, "__wrapped__", jitted)     # jitted anew: shardings bound to other devices would pin it
  cost = jax.jit(function).lower(*shapes).cost_analysis()
  if isinstance(cost, (list, tuple)):
    cost = cost[0]
  return float(cost["flops"])


def matmul_flops_per_s(n: int = 2048, reps: int = 10, shape=None) -> float:
  """Dense float32 [n, n] x [n, n] FLOP/s on the default device, best of `reps`; or of [m, k] x [k, n] for
  shape=(m, k, n)."""
  m, k, n = shape or (n, n, n)
  a = jax.random.normal(jax.random.key(0), (m, k), jnp.float32)
  b = jax.random.normal(jax.random.key(1), (k, n), jnp.float32)
  matmul = jax.jit(jnp.dot)
  matmul(a, b).block_until_ready()
  best = float("inf")
  for _ in range(reps):
    start = time.perf_counter()
    matmul(a, b).block_until_ready()
    best = min(best, time.perf_counter() - start)
  return 2.0 * m * k * n / best
