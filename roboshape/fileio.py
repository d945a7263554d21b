"""Small file writes that never leave a half-written file behind: write a sibling `.tmp`, fsync, then rename.

A reader sees the old file or the new one, never a mix; an interrupted or failed write leaves no `.tmp` behind. A
full disk is an OSError(ENOSPC) that names the file (`disk_full`, `disk_full_path` find one wherever a library
noticed it). And the tail of a log (`tail_lines`), for the one-line reports of child processes.
"""
import errno
import json
import os
import re
from typing import BinaryIO, Callable, Optional

NO_SPACE = os.strerror(errno.ENOSPC)     # "No space left on device": also how TensorFlow and TensorStore say it


def atomic_write_file(path: str, write: Callable[[BinaryIO], None]) -> None:
  """Replaces `path` atomically with what `write(f)` writes to the binary file `f` (the temporary file is removed
  if anything fails; a full disk is an OSError(ENOSPC) naming `path`)."""
  tmp = f"{path}.tmp"
  try:
    with open(tmp, "wb") as f:
      write(f)
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except BaseException as e:
    if os.path.exists(tmp):
      os.remove(tmp)
    if isinstance(e, OSError) and e.errno == errno.ENOSPC:      # named by the file meant, not its .tmp
      raise OSError(errno.ENOSPC, NO_SPACE, path) from e
    raise


def save_figure(fig, path: str, rect=(0, 0, 1, 1), dpi=None) -> str:
  """Lays a matplotlib figure out within `rect` (of the figure: left, bottom, right, top), writes it atomically to
  `path` (making its folder; the format from the extension; `dpi` None: the figure's) and closes it; returns
  `path`."""
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  fig.tight_layout(rect=rect)
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  try:
    atomic_write_file(path, lambda f: fig.savefig(f, format=os.path.splitext(path)[1][1:], dpi=dpi))
  finally:
    plt.close(fig)
  return path


def atomic_write_text(path: str, text: str) -> None:
  """Replaces `path` with `text` (UTF-8) atomically."""
  atomic_write_file(path, lambda f: f.write(text.encode("utf-8")))


def atomic_write_json(path: str, value, indent: int = 2) -> None:
  """Replaces `path` with `value` as JSON, atomically."""
  atomic_write_text(path, json.dumps(value, indent=indent))


def _chain(e: Optional[BaseException]):
  """`e`, then what caused it or was being handled when it was raised, and so on."""
  seen = set()
  while e is not None and id(e) not in seen:
    seen.add(id(e))
    yield e
    e = e.__cause__ or e.__context__


def _full(e: BaseException) -> bool:
  return (isinstance(e, OSError) and e.errno == errno.ENOSPC) or NO_SPACE in str(e)


def disk_full(e: BaseException) -> bool:
  """Whether `e`, or an error that led to it, is a full disk: OSError(ENOSPC), or a library's own error type whose
  message says so (TensorFlow's ResourceExhaustedError, TensorStore's ValueError in orbax, ...)."""
  return any(_full(x) for x in _chain(e))


def disk_full_path(e: BaseException) -> Optional[str]:
  """The file or folder that the first full-disk error in `e`'s chain names (its filename, else the first quoted
  absolute path of its message), or None when it names none."""
  for x in _chain(e):
    if _full(x):
      if isinstance(x, OSError) and x.filename:
        return str(x.filename)
      quoted = re.search(r"\"(/[^\"]+)\"", str(x))
      if quoted:
        return quoted.group(1)
  return None


def tail_lines(path: str, max_bytes: int = 16384) -> list:
  """The non-empty lines (stripped of line ends) of the last `max_bytes` of a log; OSError when it is unreadable.
  Carriage returns (progress bars) end lines too."""
  with open(path, "rb") as f:
    f.seek(0, os.SEEK_END)
    f.seek(max(0, f.tell() - max_bytes))
    text = f.read().decode("utf-8", "replace")
  return [l for l in text.replace("\r", "\n").splitlines() if l.strip()]
