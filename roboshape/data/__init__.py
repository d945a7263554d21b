"""The RoboShape dataset: expert demonstrations stored as RLDS episodes in TFDS, one dataset per task.

  path = roboshape.data.dataset_path(config, workdir)       # <config.data.dir or workdir/data>/roboshape_<task>/1.0.0
  ds = tfds.builder_from_directory(path).as_dataset(split="train")   # plain TFDS, nothing of roboshape needed

Modules: `rlds` (layout + writer), `reader` (episodes and clip batches), `collect` (the "collect" stage),
`validate` and `browse` (command-line tools). Importing this package is cheap: TensorFlow is imported only by the
modules that read or write.
"""
import os

from roboshape import rundir

VERSION = "1.0.0"
SPLITS = ("train", "val")
STATE_FILE = "roboshape.json"  # roboshape's own record of a dataset: its config, shards, seeds and checksums


def dataset_name(task: str) -> str:
  """The TFDS name of the dataset of one task, e.g. "roboshape_pick"."""
  return f"roboshape_{task}"


def dataset_path(config, workdir: str) -> str:
  """The directory `tfds.builder_from_directory` reads: <rundir.data_root>/roboshape_<task>/<VERSION>."""
  return os.path.join(rundir.data_root(config, workdir), dataset_name(config.task), VERSION)
