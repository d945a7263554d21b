"""TensorBoard scalars of a training loop, written in the loop's own thread.

  scalars = Scalars(os.path.join(root, "tb"))
  scalars.write(step, {"train/loss": 0.5, "train/lr": 1e-3})
  scalars.close()

The file is TensorBoard's (events.out.tfevents.<time>.<host>, tensorboardX's records and protos), but no thread
writes it behind the loop's back: tensorboardX's SummaryWriter writes from a thread of its own, which a full disk
(any write error) ends, after which the loop blocks for ever once the writer's queue fills. Here a failed write
raises in the loop, like every other write of the run. Written records reach the disk at least every
`flush_seconds` and at `close`. tensorboardX (which imports torch) is imported by the first Scalars, not with this
module.
"""
import os
import socket
import time
from typing import Mapping


class Scalars:
  """Scalars into a new event file in `logdir` (made if missing; an earlier run's files are kept)."""

  def __init__(self, logdir: str, flush_seconds: float = 60.0):
    # pylint: disable=import-outside-toplevel
    from tensorboardX import summary
    from tensorboardX.proto import event_pb2
    from tensorboardX.record_writer import RecordWriter
    self._summary, self._event = summary, event_pb2.Event
    os.makedirs(logdir, exist_ok=True)
    base = os.path.join(logdir, f"events.out.tfevents.{int(time.time())}.{socket.gethostname()}")
    self.path, n = base, 1
    while os.path.exists(self.path):       # a run resumed within the same second: a file of its own
      n += 1
      self.path = f"{base}.{n}"
    self._records = RecordWriter(self.path)
    self._flush_seconds, self._flushed = flush_seconds, float("-inf")     # the first values: at once
    self._write(self._event(wall_time=time.time(), file_version="brain.Event:2"))

  def _write(self, event) -> None:
    self._records.write(event.SerializeToString())

  def write(self, step: int, values: Mapping[str, float]) -> None:
    """Records each {tag: value} at `step`."""
    now = time.time()
    for tag, value in values.items():
      self._write(self._event(wall_time=now, step=int(step), summary=self._summary.scalar(tag, float(value))))
    if time.monotonic() - self._flushed >= self._flush_seconds:
      self._records.flush()
      self._flushed = time.monotonic()

  def close(self) -> None:
    """Writes what is buffered and closes the file (closed also when that write fails)."""
    try:
      self._records.flush()
    finally:
      self._records.close()
