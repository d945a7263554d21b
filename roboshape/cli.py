"""Command-line plumbing shared by launch.py and the tools: one-line errors instead of tracebacks.

`UserError` is what roboshape raises for bad input (a missing file, an unknown task, a dataset of another config):
the message says what to do, and the command exits with status 2 and no traceback.
"""
import difflib
import os
import sys
from typing import Callable, Sequence

from absl import app
from absl import flags


class UserError(Exception):
  """Bad input from the person running roboshape; the message says what to do."""


def _fail(message: str, code: int = 2) -> int:
  print(f"roboshape: error: {message}", file=sys.stderr)
  return code


def _flat_keys(config, prefix=""):
  for key, value in config.items():
    path = f"{prefix}{key}"
    if hasattr(value, "items"):
      yield from _flat_keys(value, path + ".")
    else:
      yield path


def _root_cause(e: BaseException) -> str:
  while e.__cause__ is not None or e.__context__ is not None:
    e = e.__cause__ or e.__context__
  text = str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)
  return text.strip().splitlines()[0] if text.strip() else type(e).__name__


def _check_overrides(argv: Sequence[str]) -> None:
  """Parses the flags; a bad config file or an unknown --config.x.y fails with one clear line."""
  config_args = [a for a in argv[1:] if a.startswith("--config=")]
  if config_args and "config" in flags.FLAGS:
    spec = config_args[-1].split("=", 1)[1]
    path = spec.split(":", 1)[0]
    if not os.path.isfile(path):
      raise UserError(f"config file {path!r} not found; experiments live in configs/, e.g. configs/pick_savi.py:tiny")
    try:
      config = flags.FLAGS["config"].parser.parse(spec)
    except Exception as e:  # pylint: disable=broad-except
      raise UserError(f"cannot load --config={spec}: {_root_cause(e)}") from None
    keys = set(_flat_keys(config))
    prefixes = {k.rsplit(".", i)[0] for k in keys for i in range(k.count(".") + 1)}
    for arg in argv[1:]:
      if not arg.startswith("--config."):
        continue
      key = arg.split("=", 1)[0][len("--config."):]
      if key in prefixes:
        continue
      near = difflib.get_close_matches(key, sorted(keys), n=4, cutoff=0.6)
      if not near:
        section = key.split(".")[0]
        near = sorted(k for k in keys if k.split(".")[0] == section)[:8] or sorted(k for k in keys if "." not in k)
      raise UserError(f"unknown config key {key!r}; valid keys near it: {', '.join(near)}")
  try:
    flags.FLAGS(argv)
  except Exception as e:  # pylint: disable=broad-except
    raise UserError(f"bad command-line flag: {_root_cause(e)}") from None


def run_app(main: Callable[[Sequence[str]], None], argv: Sequence[str]) -> int:
  """Runs an absl main with UserError (and bad flags) turned into a one-line message and exit status 2."""
  try:
    _check_overrides(argv)
  except UserError as e:
    return _fail(str(e))
  if flags.FLAGS["config"].present == 0 and "config" in flags.FLAGS and flags.FLAGS["config"].value is None:
    return _fail("--config is required, e.g. --config=configs/pick_savi.py:tiny")
  try:
    app.run(main, argv=[argv[0]] + [a for a in argv[1:] if not a.startswith("-")], flags_parser=lambda a: a)
  except UserError as e:
    return _fail(str(e))
  except SystemExit as e:
    return 0 if e.code is None else (e.code if isinstance(e.code, int) else 1)
  return 0
