"""The encoder registry: every frozen encoder a policy can be trained on, registered by name.

An encoder is one module that calls `register(Kind(...))` when imported, and its Kind is the only place that
says what the encoder is and needs: its name, the observation keys its step reads (`inputs`, any of
OBSERVATION_KEYS), its pretraining stage and the model that stage trains, the config sections it reads and their
checks, whether it is a baseline, and `build(config, workdir) -> FrozenEncoder`. Configs, the config check, the
stage wiring, the grid, the feature cache, closed-loop evaluation and the report all ask the registry and take any
registered name. Importing this package is cheap: each `build` and `check` imports what it needs (JAX, torch, the
model) only when called.

A grid's columns are registered encoders, alone or with options beyond the paper that set config fields
("savi+proprio": policy.proprio=True); each option is registered once in roboshape/encoders/columns.py.

Adding an encoder (README.md, "Adding an encoder"): a module here that registers its `Kind` through
roboshape/encoders/registry.py (not through this package), its import below, and
`configs/{push,pick,place}_<name>.py` (a module elsewhere registers one when it is imported:
tests/toy_encoder.py).
"""
# pylint: disable=unused-import,wrong-import-position
from roboshape.encoders.registry import FAMILIES
from roboshape.encoders.registry import Kind
from roboshape.encoders.registry import OBSERVATION_KEYS
from roboshape.encoders.registry import PretrainModel
from roboshape.encoders.registry import Selection
from roboshape.encoders.registry import build_encoder
from roboshape.encoders.registry import get
from roboshape.encoders.registry import in_family
from roboshape.encoders.registry import names
from roboshape.encoders.registry import register
from roboshape.encoders.registry import table_order
from roboshape.encoders.registry import tokens_per_frame
from roboshape.encoders.registry import unregister

# The built-in encoders, each registering itself as it is imported, in the order `names` gives them (cheap: none
# imports JAX or torch at the top).
from roboshape.encoders import savi        # noqa: F401,E402
from roboshape.encoders import baselines   # noqa: F401,E402
from roboshape.encoders import state       # noqa: F401,E402
from roboshape.encoders import objects     # noqa: F401,E402
from roboshape.encoders import poses       # noqa: F401,E402
from roboshape.encoders import ae          # noqa: F401,E402
