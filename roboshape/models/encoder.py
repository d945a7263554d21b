"""The frozen-encoder interface that SAVi, R3M and DINO share, so the policy and evaluation treat them alike.

An encoder is a pure step function over frames plus its params:

  state = enc.init_state(batch_size)
  tokens, state = enc.step(params, state, frames)        # frames uint8 [B, H, W, 3] -> tokens float32 [B, N, D]

N is the number of tokens per frame (K slots for SAVi, 1 for a global encoder, 1 + patches for DINO with patch
tokens) and D their width. `encode_episode` runs the step over a whole episode with `jax.lax.scan`, so the features
a policy is trained on (cached once per dataset) are exactly those closed-loop control sees frame by frame.
"""
import dataclasses
from typing import Any, Callable, Tuple

import jax
import jax.numpy as jnp

State = Any
StepFn = Callable[[Any, State, jax.Array], Tuple[jax.Array, State]]


@dataclasses.dataclass(frozen=True)
class FrozenEncoder:
  """A frozen image or video encoder.

  Attributes:
    name: "savi", "r3m" or "dino".
    params: the encoder's parameters (a pytree of arrays).
    step: pure `(params, state, frames uint8 [B,H,W,3]) -> (tokens [B,N,D], state)`.
    init_state: `batch_size -> state` (an empty tuple for encoders without memory).
    num_tokens: N.
    token_dim: D.
    identity: a string that changes whenever the weights change (a checkpoint's path + step, a file's hash);
      feature caches are keyed by it.
  """
  name: str
  params: Any
  step: StepFn
  init_state: Callable[[int], State]
  num_tokens: int
  token_dim: int
  identity: str

  def encode_episode(self, frames: jax.Array) -> jax.Array:
    """uint8 [T, H, W, 3] -> tokens [T, N, D], recurrent over the whole episode."""
    return self.encode_batch(frames[None])[0]

  def encode_batch(self, videos: jax.Array) -> jax.Array:
    """uint8 [B, T, H, W, 3] -> tokens [B, T, N, D]; episodes of one batch must share their length T."""
    return _encode_batch(self.step, self.params, self.init_state(videos.shape[0]), videos)


@jax.jit(static_argnums=0)
def _encode_batch(step: StepFn, params, state, videos):
  def body(carry, frames):
    tokens, carry = step(params, carry, frames)
    return carry, tokens
  _, tokens = jax.lax.scan(body, state, jnp.swapaxes(videos, 0, 1))
  return jnp.swapaxes(tokens, 0, 1)
