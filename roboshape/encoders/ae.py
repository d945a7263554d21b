"""`ae`: a holistic frame autoencoder pretrained on the task's frames exactly as SAVi is, then frozen (one token per
frame): the in-domain baseline that holds pretraining equal and takes the objects away (roboshape/models/ae.py,
roboshape/train/pretrain_ae.py)."""
from roboshape import encoders


def _build(config, workdir: str):
  del config
  from roboshape.train import pretrain_ae  # pylint: disable=import-outside-toplevel
  return pretrain_ae.load_encoder(workdir)


encoders.register(encoders.Kind(
    name="ae", inputs=("image",), pretrain="roboshape.train.pretrain_ae", build=_build, title="AE",
    description="a frame autoencoder with SAVi's CNN and decoder, pretrained like SAVi on the task's frames "
                "(one latent per frame; control: in-domain pretraining without objects)"))
