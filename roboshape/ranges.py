"""Ranges of config fields, declared once as data beside what owns the field, and checked with one line each.

  RANGES = (ranges.Int("savi.num_slots", 1, "slots per frame"),
            ranges.Number("pretrain.train.learning_rate", 0.0, "the peak learning rate", low_ok=False))
  ranges.check(config, RANGES)    # roboshape.errors.UserError "<field>=<value>: use ... (<what it is>)." for the first

An encoder's own sections are declared with its registration (roboshape/encoders, Kind.check), a stage's sections
in the module that reads them (e.g. roboshape/train/pretrain.py RANGES), the rest in roboshape/config_check.py. Importing this module imports nothing but the errors.
"""
import dataclasses
import math
import numbers
from typing import Any, Iterable, Optional, Sequence, Tuple

from roboshape import fields
from roboshape.errors import UserError


def value(config, path: str) -> Any:
  """config's field at dotted `path`; a UserError when it is absent."""
  try:
    return fields.get(config, path)
  except KeyError:
    raise UserError(f"the config has no field {path}; build configs with configs/common.py "
                    "(e.g. configs/pick_savi.py) and override fields with --config.<field>=<value>.") from None


def is_int(x: Any) -> bool:
  return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def is_number(x: Any) -> bool:
  return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x)


def choices(values: Iterable[Any]) -> str:
  return ", ".join(str(v) for v in values)


@dataclasses.dataclass(frozen=True)
class Int:
  """An int >= low."""
  path: str
  low: int
  what: str

  def check(self, config) -> int:
    x = value(config, self.path)
    if not is_int(x) or x < self.low:
      raise UserError(f"{self.path}={x!r}: use an int >= {self.low} ({self.what}).")
    return int(x)


@dataclasses.dataclass(frozen=True)
class Number:
  """A finite number >= low (> low unless low_ok), and <= high when high is given."""
  path: str
  low: float
  what: str
  low_ok: bool = True
  high: Optional[float] = None

  def check(self, config) -> float:
    x = value(config, self.path)
    above = is_number(x) and (x >= self.low if self.low_ok else x > self.low)
    if not above or (self.high is not None and x > self.high):
      if self.high is not None:
        wanted = f"a number in [{self.low:g}, {self.high:g}]"
      else:
        wanted = f"a number {'>=' if self.low_ok else '>'} {self.low:g}"
      raise UserError(f"{self.path}={x!r}: use {wanted} ({self.what}).")
    return float(x)


@dataclasses.dataclass(frozen=True)
class Choice:
  """One of `options`."""
  path: str
  options: Tuple[Any, ...]
  what: str

  def check(self, config) -> Any:
    x = value(config, self.path)
    if x not in tuple(self.options):
      raise UserError(f"{self.path}={x!r}: use one of {choices(self.options)} ({self.what}).")
    return x


@dataclasses.dataclass(frozen=True)
class Ints:
  """A tuple of ints >= low: non-empty unless `empty_ok`, as long as the tuple at `length_of` when that is given (one
  entry per entry of it), without repeats when `distinct`."""
  path: str
  low: int
  what: str
  length_of: str = ""
  empty_ok: bool = False
  distinct: bool = False

  def check(self, config) -> Tuple[int, ...]:
    x = value(config, self.path)
    ok = (isinstance(x, (tuple, list)) and (len(x) or self.empty_ok) and all(is_int(v) and v >= self.low for v in x)
          and (not self.distinct or len(set(x)) == len(x)))
    if not ok:
      kind = ("a" if self.empty_ok else "a non-empty") + " tuple of" + (" distinct" if self.distinct else "")
      raise UserError(f"{self.path}={x!r}: use {kind} ints >= {self.low} ({self.what}).")
    if self.length_of:
      length = len(value(config, self.length_of))
      if len(x) != length:
        raise UserError(f"{self.path}={tuple(x)!r} has {len(x)} entries: use {length} ({self.what}).")
    return tuple(int(v) for v in x)


@dataclasses.dataclass(frozen=True)
class Flag:
  """True or False."""
  path: str
  what: str

  def check(self, config) -> bool:
    x = value(config, self.path)
    if not isinstance(x, bool):
      raise UserError(f"{self.path}={x!r}: use True or False ({self.what}).")
    return x


def check(config, declared: Sequence[Any]) -> None:
  """Raises UserError for the first field of `declared` (Int, Number, Choice, Ints, Flag) out of its range."""
  for field in declared:
    field.check(config)
