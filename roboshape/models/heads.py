"""The Gaussian-mixture action head: M diagonal Gaussians over the (normalised) action, mixed by learned weights.

  head = GMMHead(action_dim=7, num_modes=5)
  gmm = head(features)                                  # features [..., F] -> GMM with [..., M, A] leaves
  nll = -gmm_log_prob(gmm, actions)                     # actions [..., A] -> [...]
  a = gmm_mean(gmm)                                     # [..., A]: the mixture mean (the default eval action)
  a = gmm_sample(gmm, rng, noise=0.1)                   # a mode drawn by its weight, its mean plus scaled noise

The head puts tanh on the means (actions are normalised to [-1, 1]) and softplus plus a floor on the scales.
The mixture is written by hand with `jax.scipy.stats.norm.logpdf` and `jax.nn.log_softmax` / `jax.nn.logsumexp`
rather than with distrax's `MixtureSameFamily` (or TensorFlow Probability's JAX substrate), which roboshape does not
use: the head needs only a log-density, a mean and a sample, each a few lines the test suite checks against
scipy's densities, and writing them keeps distrax and TFP (whose JAX substrate needs a nightly build under the
jax version roboshape pins) out of the dependencies.
"""
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp


class GMM(NamedTuple):
  """A batch of mixtures of diagonal Gaussians.

  Attributes:
    logits: [..., M] unnormalised log mixture weights (M modes).
    means: [..., M, A] in (-1, 1).
    scales: [..., M, A] standard deviations, > 0.
  """
  logits: jax.Array
  means: jax.Array
  scales: jax.Array


def gmm_log_prob(gmm: GMM, x: jax.Array) -> jax.Array:
  """log p(x) of `x` [..., A] under the mixture -> [...]."""
  per_dim = jax.scipy.stats.norm.logpdf(x[..., None, :], loc=gmm.means, scale=gmm.scales)   # [..., M, A]
  per_mode = jnp.sum(per_dim, axis=-1) + jax.nn.log_softmax(gmm.logits, axis=-1)           # [..., M]
  return jax.nn.logsumexp(per_mode, axis=-1)


def gmm_mean(gmm: GMM) -> jax.Array:
  """The mixture mean [..., A]."""
  weights = jax.nn.softmax(gmm.logits, axis=-1)
  return jnp.sum(weights[..., None] * gmm.means, axis=-2)


def gmm_sample(gmm: GMM, rng: jax.Array, noise: float = 0.1) -> jax.Array:
  """A low-noise sample [..., A]: a mode drawn by its weight, its mean plus `noise` x its scale x N(0, 1).

  noise=1 samples the mixture itself; small values stay near the chosen mode's mean.
  """
  mode_rng, noise_rng = jax.random.split(rng)
  mode = jax.random.categorical(mode_rng, gmm.logits, axis=-1)                               # [...]
  pick = lambda v: jnp.take_along_axis(v, mode[..., None, None], axis=-2)[..., 0, :]
  mean, scale = pick(gmm.means), pick(gmm.scales)
  return jnp.clip(mean + noise * scale * jax.random.normal(noise_rng, mean.shape), -1.0, 1.0)


class GMMHead(nn.Module):
  """features [..., F] -> a GMM over one action of `action_dim` dims, with `num_modes` modes.

  Attributes:
    action_dim: A.
    num_modes: M.
    min_scale: floor added to the softplus scales.
    hidden: width of the MLP before the output layer (0: a single linear layer).
  """
  action_dim: int = 7
  num_modes: int = 5
  min_scale: float = 1e-4
  hidden: int = 256

  @nn.compact
  def __call__(self, features: jax.Array) -> GMM:
    m, a = self.num_modes, self.action_dim
    h = features
    if self.hidden:
      h = nn.gelu(nn.Dense(self.hidden, name="hidden")(h))
    lead = h.shape[:-1]
    logits = nn.Dense(m, name="logits")(h)
    means = jnp.tanh(nn.Dense(m * a, name="means")(h).reshape(*lead, m, a))
    scales = jax.nn.softplus(nn.Dense(m * a, name="scales")(h).reshape(*lead, m, a)) + self.min_scale
    return GMM(logits, means, scales)
