"""Progress bars for every long loop (collection, pretraining, the feature cache, behaviour cloning, rollouts).

On a terminal a bar is tqdm's own, redrawn in place. Written to a file (a grid lane's log.txt, a run under nohup)
tqdm would redraw it with a carriage return ten times a second: one line of megabytes that `tail`, `grep` and
`less` cannot read. There each refresh is a line of its own instead, at most one every LOG_INTERVAL seconds, and
the lines between them (a stage's metrics, tqdm.write's messages) keep their order.
"""
import sys
from typing import Any, Iterable, Optional, TextIO

from tqdm import tqdm

LOG_INTERVAL = 60.0      # seconds between a bar's lines in a file


class _Lines:
  """A stream for tqdm that ends each redraw of the bar with a newline rather than starting it with a carriage
  return; the blanks tqdm pads or clears a line with are dropped, and so is a redraw the same as the line before
  it (a closing bar draws its last state again)."""

  def __init__(self, stream: TextIO):
    self._stream = stream
    self._last = None

  def write(self, text: str) -> None:
    line = text.replace("\r", "").rstrip()
    if line and line != self._last:
      if sys.stdout is not None and self._stream is not sys.stdout:
        sys.stdout.flush()      # what was printed before this line comes before it where both share a file
      self._stream.write(line + "\n")
      self._last = line

  def flush(self) -> None:
    self._stream.flush()


def _terminal(stream: Any) -> bool:
  try:
    return bool(stream.isatty())
  except (AttributeError, ValueError):    # no isatty, or a closed stream
    return False


def bar(iterable: Optional[Iterable] = None, file: Optional[TextIO] = None, **kwargs) -> tqdm:
  """tqdm(iterable, **kwargs) writing to `file` (sys.stderr): as it is on a terminal, else a line at most every
  LOG_INTERVAL seconds (the first and the last always)."""
  stream = sys.stderr if file is None else file
  if not _terminal(stream):
    kwargs["mininterval"] = max(kwargs.get("mininterval", 0.0), LOG_INTERVAL)
    kwargs["maxinterval"] = max(kwargs.get("maxinterval", 0.0), LOG_INTERVAL)
    stream = _Lines(stream)
  return tqdm(iterable, file=stream, **kwargs)
