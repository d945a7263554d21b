"""SAVi, the object-centric video encoder, pretrained in the run's workdir (roboshape/train/pretrain.py)."""
from roboshape import encoders


def _build(config, workdir: str):
  del config
  from roboshape.train import pretrain  # pylint: disable=import-outside-toplevel
  return pretrain.load_encoder(workdir)


encoders.register(encoders.Kind(
    name="savi", inputs=("image",), pretrain="roboshape.train.pretrain", build=_build, title="SAVi",
    description="slot attention for video, pretrained on the task's frames (K slots per frame)"))
