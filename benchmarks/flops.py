"""What the benchmarks measure FLOP rates with: a compiled function's FLOPs and the machine's dense-matmul FLOP/s."""
import time

import jax
import jax.numpy as jnp


def compiled_flops(compiled) -> float:
  """FLOPs of one call of a compiled jax function, from XLA's cost analysis."""
  cost = compiled.cost_analysis()
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
