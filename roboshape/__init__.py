"""roboshape: does an object-centric representation make robot manipulation policies better and more robust?

Notebook entry points (imports are lazy, so `import roboshape` is cheap and pulls in neither TensorFlow nor SAPIEN):

  enc = roboshape.load_encoder(workdir)     # the run's frozen encoder (SAVi from its checkpoint, or a baseline)
  policy = roboshape.load_policy(workdir)   # policy.reset(); action = policy.act(frame)

Both restore parameters only (no optimizer state is read or built). The run folder's layout is roboshape/rundir.py.
"""


def load_encoder(workdir: str):
  """The frozen encoder of the run in `workdir`, as a `roboshape.models.encoder.FrozenEncoder`."""
  from roboshape import encoders  # pylint: disable=import-outside-toplevel
  from roboshape import rundir  # pylint: disable=import-outside-toplevel
  return encoders.build_encoder(rundir.load_config(workdir), workdir)


def load_policy(workdir: str):
  """The trained policy of the run in `workdir`, ready for closed-loop control."""
  from roboshape.train import bc  # pylint: disable=import-outside-toplevel
  return bc.load_policy(workdir)
