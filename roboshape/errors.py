"""What roboshape raises for bad input.

`UserError` is bad input from the person running roboshape (a missing file, an unknown task, a dataset of another
config): its message says what to do, and launch.py and the tools print it as one line and exit with status 2
(roboshape/cli.py).
"""


class UserError(Exception):
  """Bad input from the person running roboshape; the message says what to do."""
