"""A grid's columns: a registered encoder alone ("savi"), or with options beyond the paper ("savi+proprio").

  encoder, fields = parse("savi+proprio")      # "savi", {"policy.proprio": True}
  apply(config, "savi+proprio")               # config.encoder = "savi", config.policy.proprio = True
  of_config(config)                           # "savi+proprio": the column a config is
  title("savi+proprio")                       # "SAVi+proprio", its name in tables

A column's name is its encoder's, then "+<option>" for each option it turns on, in the order of OPTIONS. Each
option is registered here once, with the config fields it sets, so the name is read both ways: the grid and
configs/common.py turn a name into a config (`parse`, `apply`), and the evaluation labels its rollouts with the column
its config is (`of_config`), which names the run's folder, its published folder (<task>_<column>/) and the report's
column. A name a grid gives a run and the one its results carry are thus the same by construction; a config that turns
an option on by hand (--config.policy.proprio=True) is that option's column too.

An option whose fields all lie in the policy section changes nothing its encoder's pretraining reads
(`policy_only`): its column may serve the encoder pretrained by the plain column's run (roboshape/grid.py).
"""
import dataclasses
from typing import Any, Dict, Tuple

from roboshape import fields as fields_lib
from roboshape.encoders import registry
from roboshape.envs import camera
from roboshape.errors import UserError

SEPARATOR = "+"


@dataclasses.dataclass(frozen=True)
class Option:
  """An option beyond the paper: `fields` ((dotted config field, value) pairs) it sets, what it is, and the encoders
  it applies to (`encoders`; () for every one)."""
  name: str
  fields: Tuple[Tuple[str, Any], ...]
  description: str
  encoders: Tuple[str, ...] = ()


OPTIONS = {o.name: o for o in (
    Option("cond", (("savi.init_mean", "cues"),),
           "conditional SAVi: its first slots are encoded from each object's box in the first frame's segmentation "
           "(privileged: the simulator's view of where every object is at the first frame; roboshape/models/savi.py)",
           encoders=("savi",)),
    Option("proprio", (("policy.proprio", True),),
           "the robot's own pose as one more token per frame (roboshape/encoders/proprio.py)"),
    Option("rel", (("policy.hand_relative", True),),
           "with proprio: each token's object relative to the hand (roboshape/encoders/proprio.py)"),
    Option("wrist", (("env.cameras", (camera.FRONT, camera.WRIST)),),
           "a second camera on the hand: the encoder reads the front and the wrist views (roboshape/encoders/"
           "views.py; a dataset collected with both)"),
)}


def parse(column: str) -> Tuple[str, Dict[str, Any]]:
  """(registered encoder, {dotted field: value} its options set) of a column's name; a UserError naming the
  choices for an unknown encoder or option, or options out of OPTIONS' order or repeated (one name per column)."""
  if not isinstance(column, str) or not column:
    raise UserError(f"column {column!r}: use a registered encoder's name, alone or with options "
                    f"({_choices()}).")
  encoder, *options = column.split(SEPARATOR)
  if encoder not in registry.names():
    raise UserError(f"unknown encoder {encoder!r} in column {column!r}; registered encoders: "
                    f"{', '.join(registry.names())} (options: {_choices()}).")
  unknown = [o for o in options if o not in OPTIONS]
  if unknown:
    raise UserError(f"unknown option {unknown[0]!r} in column {column!r}; options: {_choices()}.")
  foreign = [o for o in options if o in OPTIONS and OPTIONS[o].encoders and encoder not in OPTIONS[o].encoders]
  if foreign:
    raise UserError(f"option {foreign[0]!r} in column {column!r} applies to "
                    f"{', '.join(OPTIONS[foreign[0]].encoders)} only.")
  order = [o for o in OPTIONS if o in options]
  if options != order:
    raise UserError(f"column {column!r} names its options out of order or twice; write it "
                    f"{SEPARATOR.join([encoder] + order)!r}.")
  return encoder, {f: v for o in options for f, v in OPTIONS[o].fields}


def _choices() -> str:
  return ", ".join(f"{SEPARATOR}{o.name}: {o.description}" for o in OPTIONS.values())


def apply(config, column: str) -> None:
  """Sets config.encoder to the column's encoder and the fields its options set."""
  encoder, settings = parse(column)
  config.encoder = encoder
  for field, value in settings.items():
    fields_lib.put(config, field, value)


def of_config(config) -> str:
  """The column `config` (a ConfigDict, or a config.json's dict) is: its encoder, then each option whose fields
  all hold the values the option sets."""
  on = [o.name for o in OPTIONS.values() if (not o.encoders or config["encoder"] in o.encoders)
        and all(_same(fields_lib.get(config, f, None), v) for f, v in o.fields)]
  return SEPARATOR.join([config["encoder"]] + on)


def _same(value, setting) -> bool:
  """Whether a config's `value` is an option's `setting`; a config.json holds a tuple as a list."""
  return (tuple(value) if isinstance(value, list) else value) == setting


def policy_only(column: str) -> bool:
  """Whether every field the column's options set is in the policy section, which its encoder's pretraining
  never reads (True for a column without options)."""
  return all(field.startswith("policy.") for field in parse(column)[1])


def flags(column: str) -> str:
  """The command-line overrides that turn an experiment config of the column's encoder into the column:
  " --config.policy.proprio=True" ("" for a plain encoder)."""
  return "".join(f" --config.{field}={value!r}" for field, value in parse(column)[1].items())


def title(column: str) -> str:
  """The column's name in tables: its encoder's title, then its options ("SAVi+proprio")."""
  encoder, *options = column.split(SEPARATOR)
  parse(column)
  return SEPARATOR.join([registry.get(encoder).title] + options)
