"""Image preprocessing shared by the R3M and DINO encoders: uint8 frames -> resized, ImageNet-normalised floats."""
import jax
import jax.numpy as jnp

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def imagenet_input(frames: jax.Array, size: int) -> jax.Array:
  """uint8 (or [0, 255] float) [B, H, W, 3] -> float32 [B, size, size, 3], ImageNet-normalised.

  The frames are scaled to [0, 1], resized bilinearly (half-pixel centres, as torch's `interpolate` with
  align_corners=False; antialiased when shrinking) unless `size` is 0 or already their side, then normalised
  with the ImageNet mean and standard deviation.
  """
  x = frames.astype(jnp.float32) / 255.0
  if size and x.shape[1:3] != (size, size):
    x = jax.image.resize(x, (x.shape[0], size, size, x.shape[3]), method="linear", antialias=True)
  return (x - jnp.asarray(IMAGENET_MEAN, jnp.float32)) / jnp.asarray(IMAGENET_STD, jnp.float32)
