"""Data parallelism over this process's devices: a 1-D mesh ("data"), state replicated, batches split on axis 0.

Both train loops shard this way: SAVi's (and the AE's) pretraining and behaviour cloning. With one device (a CPU as
JAX sees it by default) this is plain single-device training. A multi-GPU machine splits every batch over its
GPUs. On a CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N makes JAX see N devices, and a run on N cores
then runs a step's halves side by side (benchmarks/bc_speed.py measures what that gives the BC step).

  dp = DataParallel()
  dp.check_batch(config.policy.train.batch_size, "policy.train.batch_size")   # UserError unless it splits
  state = jax.device_put(state, dp.replicated)
  batch = dp.put_batch(numpy_batch)                                          # every leaf split on axis 0
"""
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from roboshape.errors import UserError


class DataParallel:
  """The mesh over all local devices, and the two shardings the train loops use."""

  def __init__(self):
    self.mesh = Mesh(np.array(jax.devices()), ("data",))
    self.num_devices = self.mesh.size
    self.replicated = NamedSharding(self.mesh, PartitionSpec())
    self.batch = NamedSharding(self.mesh, PartitionSpec("data"))

  def check_batch(self, batch_size: int, name: str) -> None:
    """Raises a one-line UserError when a batch of `batch_size` does not split evenly over the devices."""
    if int(batch_size) % self.num_devices:
      raise UserError(f"{name}={batch_size} does not split over {self.num_devices} devices; use a multiple of "
                      f"{self.num_devices}.")

  def put_batch(self, batch):
    """A pytree of host arrays [B, ...] placed on the mesh, split along the batch axis."""
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(self.batch, np.asarray(x)), batch)
