"""Data parallelism over this process's devices: a 1-D mesh ("data"), state replicated, batches split on axis 0.

Both train loops shard this way: SAVi's (and the AE's) pretraining and behaviour cloning. With one device (a CPU as
JAX sees it by default) this is plain single-device training. A multi-GPU machine splits every batch over its
GPUs. On a CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N makes JAX see N devices (launch.py sets N to
the process's cores: roboshape/cli.py), and a step's parts then run side by side (benchmarks/bc_speed.py,
savi_speed.py measure what that gives).

  dp = DataParallel(train_batch, val_batch)     # the most devices that split every one of these batch sizes
  state = jax.device_put(state, dp.replicated)
  batch = dp.put_batch(numpy_batch)              # every leaf split on axis 0
"""
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec



class DataParallel:
  """The mesh over the first k local devices, k the largest count (at most all of them) that splits every batch
  size given evenly, and the two shardings the train loops use. (64 and 128 on 3 devices: k = 2.)"""

  def __init__(self, *batch_sizes: int):
    devices = jax.devices()
    k = len(devices)
    while k > 1 and any(int(b) % k for b in batch_sizes):
      k -= 1
    self.mesh = Mesh(np.array(devices[:k]), ("data",))
    self.num_devices = k
    self.replicated = NamedSharding(self.mesh, PartitionSpec())
    self.batch = NamedSharding(self.mesh, PartitionSpec("data"))

  def put_batch(self, batch):
    """A pytree of host arrays [B, ...] placed on the mesh, split along the batch axis."""
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(self.batch, np.asarray(x)), batch)
