"""One dotted field of a config ("policy.train.steps"), read and written the same way everywhere: in a ConfigDict
(a config being built or checked) or in a config.json's dict (a saved run's record).

  fields.get(config, "policy.train.steps")          # the value; KeyError naming the field where it is absent
  fields.get(saved, "policy.frame_pool", None)      # the value, or the default given where it is absent
  fields.put(config, "policy.proprio", True)        # sets an existing field's leaf (a ConfigDict checks its type)
  fields.put(saved, "pretrain.train.x", 1, create=True)   # makes the missing sections of a dict on the way
  fields.put(config, *fields.parse("savi.decoder.strides=(2, 2)"))   # "field=VALUE", VALUE a Python literal
"""
import ast
from typing import Any, Tuple

_ABSENT = object()


def get(tree, dotted: str, default: Any = _ABSENT) -> Any:
  """The field of `tree` at `dotted`; where it is absent, `default` when one is given, else a KeyError(dotted)."""
  node = tree
  for key in dotted.split("."):
    if not hasattr(node, "keys") or key not in node:
      if default is _ABSENT:
        raise KeyError(dotted)
      return default
    node = node[key]
  return node


def put(tree, dotted: str, value: Any, create: bool = False) -> None:
  """Sets the field of `tree` at `dotted` to `value`. Its sections must exist (a KeyError naming the first that does
  not), unless `create`, which adds them as dicts (for a config.json's dict)."""
  *parents, leaf = dotted.split(".")
  node = tree
  for key in parents:
    if key not in node:
      if not create:
        raise KeyError(dotted)
      node[key] = {}
    node = node[key]
  node[leaf] = value


def parse(item: str) -> Tuple[str, Any]:
  """("dotted.field", value) of "dotted.field=VALUE", VALUE a Python literal (ValueError or SyntaxError if not)."""
  field, _, value = item.partition("=")
  return field, ast.literal_eval(value)
