"""The frozen-encoder interface that SAVi, R3M and DINO share, so the policy and evaluation treat them alike.

An encoder is a pure step function over frames plus its params:

  state = enc.init_state(batch_size)
  tokens, state = enc.step(params, state, frames)        # frames uint8 [B, H, W, 3] -> tokens float32 [B, N, D]

An encoder reads the observation keys named by its `inputs` (roboshape.encoders.OBSERVATION_KEYS: image,
segmentation, depth, state). Its step takes the image array itself when `inputs == ("image",)` (SAVi, R3M, DINO),
and otherwise a dict of the arrays it names; `select` makes either from an observation dict, so the cache and the
controller feed every encoder alike.

N is the number of tokens per frame (K slots for SAVi, 1 for a global encoder, 1 + patches for DINO with patch
tokens) and D their width. `encode_episode` runs the step over a whole episode with `jax.lax.scan`, so the features
a policy is trained on (cached once per dataset) are exactly those closed-loop control sees frame by frame.
"""
import dataclasses
from typing import Any, Callable, Mapping, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp

State = Any
StepFn = Callable[[Any, State, jax.Array], Tuple[jax.Array, State]]


@dataclasses.dataclass(frozen=True)
class FrozenEncoder:
  """A frozen image or video encoder.

  Attributes:
    name: the registered name (roboshape.encoders).
    params: the encoder's parameters (a pytree of arrays).
    step: pure `(params, state, obs) -> (tokens [B,N,D], state)`; obs as `select` gives it (frames uint8
      [B,H,W,3] for an image encoder).
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
  inputs: Tuple[str, ...] = ("image",)
  # tokens [B, N, D] -> (world points [B, N, 3] in metres, valid bool [B, N]): where each token's object is, for an
  # encoder whose tokens carry it (policy.hand_relative, roboshape/encoders/proprio.py); None: they do not
  points: Optional[Callable] = None

  def encode_episode(self, episode) -> jax.Array:
    """frames uint8 [T, H, W, 3] (or a dict of [T, ...] observations) -> tokens [T, N, D], recurrent over the
    whole episode."""
    return self.encode_batch(jax.tree.map(lambda x: x[None], select(self.inputs, episode)))[0]

  def encode_batch(self, videos) -> jax.Array:
    """frames uint8 [B, T, H, W, 3] (or a dict of [B, T, ...] observations) -> tokens [B, T, N, D]; episodes of one
    batch must share their length T."""
    videos = select(self.inputs, videos)
    batch = jax.tree.leaves(videos)[0].shape[0]
    return _encode_batch(self.step, self.params, self.init_state(batch), videos)


def select(inputs: Sequence[str], obs):
  """What an encoder's step takes from `obs` (a dict of arrays, or an image array): the image array for an encoder
  of inputs ("image",), otherwise the dict of its inputs. KeyError names a missing key."""
  if not isinstance(obs, Mapping):
    obs = {"image": obs}
  missing = [k for k in inputs if k not in obs]
  if missing:
    raise KeyError(f"the observation lacks {', '.join(missing)} (it has {', '.join(obs)})")
  return obs["image"] if tuple(inputs) == ("image",) else {k: obs[k] for k in inputs}


@jax.jit(static_argnums=0)
def _encode_batch(step: StepFn, params, state, videos):
  def body(carry, frames):
    tokens, carry = step(params, carry, frames)
    return carry, tokens
  _, tokens = jax.lax.scan(body, state, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), videos))
  return jnp.swapaxes(tokens, 0, 1)
