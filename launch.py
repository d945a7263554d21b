"""roboshape's one entry point: runs the stages an experiment config names.

  python launch.py --config=configs/pick_savi.py[:variant] [--workdir=runs/pick_savi] [--config.a.b=value ...]

Stages run in the order of `config.stages`; each resumes where a killed run stopped. The config is saved as
<workdir>/config.json so a notebook can rebuild what ran (`roboshape.load_policy(workdir)`). A workdir whose
stages' output was made with other settings is refused in one line; `--redo=STAGE[,STAGE]` sets that output aside
and runs those stages again (roboshape/train/fingerprint.py).
"""
import sys

from absl import app
from absl import flags
from absl import logging
from ml_collections import config_flags

from roboshape import cli

cli.host_device_per_core()   # before jax starts: the train loops split each batch over this process's cores
_CONFIG = config_flags.DEFINE_config_file("config", None, "Experiment config: configs/<exp>.py[:variant].",
                                          lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Where the run writes everything (default: runs/<config.name>).")
_REDO = flags.DEFINE_list("redo", [], "Stages (collect, pretrain, train_policy) whose output in the workdir was made "
                          "with other settings than this config's: set it aside and run the stage again.")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {' '.join(argv[1:])}")
  from roboshape import stages  # pylint: disable=import-outside-toplevel
  logging.set_verbosity(logging.WARNING)  # orbax logs every save at INFO; progress bars say what runs
  config = _CONFIG.value
  workdir = _WORKDIR.value or f"runs/{config.name}"
  stages.run(config, workdir, redo=tuple(_REDO.value))


if __name__ == "__main__":
  cli.exit_process(cli.run_app(main, sys.argv))
