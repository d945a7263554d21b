"""What roboshape raises for bad input.

`UserError` is bad input from the person running roboshape (a missing file, an unknown task, a dataset of another
config): its message says what to do, and launch.py and the tools print it as one line and exit with status 2
(roboshape/cli.py). `DiskFull` is the one for a disk that filled up while a stage wrote: its message names what
could not be written and says to free space and run the same command again, which resumes.
"""
import sys

PREFIX = "roboshape: error: "    # the start of the one line on stderr (launch.py, the tools, a grid's lanes)


def print_error(message) -> int:
  """Prints `message` as roboshape's one error line on stderr; returns 2, the exit status of bad input."""
  print(f"{PREFIX}{message}", file=sys.stderr, flush=True)
  return 2


class UserError(Exception):
  """Bad input from the person running roboshape; the message says what to do."""


class DiskFull(UserError):
  """A full disk stopped a stage; the message starts with DiskFull.PREFIX. Not a reason to skip a grid's run: the
  grid stops (roboshape/stages.py), since every run after it would meet the same disk."""
  PREFIX = "disk full"
