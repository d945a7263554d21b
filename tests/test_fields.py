"""roboshape/fields.py: the one way a dotted config field is read and written, in a ConfigDict and in a dict."""
import ml_collections
import pytest

from configs import common
from roboshape import fields


def test_get_and_put_agree_on_a_config_and_on_its_saved_dict():
  config = common.get_config("pick", "objects", "tiny")
  saved = config.to_dict()
  for tree in (config, saved):
    assert fields.get(tree, "policy.train.steps") == 20
    fields.put(tree, "policy.train.steps", 7)
    assert fields.get(tree, "policy.train.steps") == 7
    assert fields.get(tree, "policy.no_such_field", None) is None
    assert fields.get(tree, "policy.train.steps.deeper", "absent") == "absent"   # a leaf has no fields
    with pytest.raises(KeyError, match="policy.no_such_field"):
      fields.get(tree, "policy.no_such_field")
    with pytest.raises(KeyError, match="nowhere.x"):
      fields.put(tree, "nowhere.x", 1)
  fields.put(saved, "nowhere.deep.x", 1, create=True)
  assert saved["nowhere"] == {"deep": {"x": 1}}


def test_put_on_a_config_keeps_its_type_check_and_parse_reads_a_literal():
  config = ml_collections.ConfigDict({"a": {"b": 1}})
  with pytest.raises(TypeError):
    fields.put(config, "a.b", "one")
  assert fields.parse("savi.decoder.strides=(2, 2)") == ("savi.decoder.strides", (2, 2))
  with pytest.raises((ValueError, SyntaxError)):
    fields.parse("a.b=not a literal")
  with pytest.raises(ValueError):
    fields.parse("a.b=print")
