"""Small file writes that never leave a half-written file behind: write a sibling `.tmp`, fsync, then rename.

A reader sees the old file or the new one, never a mix; an interrupted write leaves no `.tmp` behind. And the
tail of a log (`tail_lines`), for the one-line reports of child processes.
"""
import json
import os


def atomic_write_text(path: str, text: str) -> None:
  """Replaces `path` with `text` atomically (the temporary file is removed if anything fails)."""
  tmp = f"{path}.tmp"
  try:
    with open(tmp, "w", newline="") as f:
      f.write(text)
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except BaseException:
    if os.path.exists(tmp):
      os.remove(tmp)
    raise


def atomic_write_json(path: str, value, indent: int = 2) -> None:
  """Replaces `path` with `value` as JSON, atomically."""
  atomic_write_text(path, json.dumps(value, indent=indent))


def tail_lines(path: str, max_bytes: int = 16384) -> list:
  """The non-empty lines (stripped of line ends) of the last `max_bytes` of a log; OSError when it is unreadable.
  Carriage returns (progress bars) end lines too."""
  with open(path, "rb") as f:
    f.seek(0, os.SEEK_END)
    f.seek(max(0, f.tell() - max_bytes))
    text = f.read().decode("utf-8", "replace")
  return [l for l in text.replace("\r", "\n").splitlines() if l.strip()]
