"""The object-centric transformer policy: a causal trunk over the history of frame tokens with [ACT] read-outs.

Tokens. For each of the last T <= H frames, its N encoder tokens (K SAVi slots, or a baseline's global token)
are projected to the trunk width and get that frame's learned time embedding (position 0 is the oldest frame of
the window). Slots of one frame get no order: the per-token projection and attention are permutation-equivariant,
so permuting the slots of a frame leaves every [ACT] output unchanged.

[ACT] tokens. A learnable [ACT] vector, plus the time embedding of the frame it reads out at, is appended after
the observation tokens, one per requested read-out frame q (`act_frames`). Attention mask:
  - observation token of frame f  -> observation tokens of frames <= f (causal over time, all slots of a frame);
  - [ACT] token of frame q        -> observation tokens of frames <= q, and itself;
  - no token attends to another [ACT] token;
  - no token attends to an observation token that is all exactly zero (padding: the `objects` encoder's token of
    an absent object), except itself. SAVi slots, global features and the state token are never all zero, so for
    them this changes nothing; for padded frames the output is as if the padding were not there.
So the [ACT] token of the last frame sees every history token and no later one, and [ACT] tokens never change
the observation stream (the last block updates the [ACT] tokens only, since nothing reads the rest): training reads out at every frame of a window (one next-action target each), while
control reads out at the newest frame only, with the same outputs. Because of the causal mask, the first q + 1
frames of a window are themselves a valid window, so episode starts need no padding: at step t < H the policy
reads out at position t of a window that holds frames 0..t (see roboshape/train/bc.py).

  net = PolicyNet(width=256, num_layers=8, num_heads=4, max_history=10)
  gmm = net.apply(params, tokens, act_frames)   # tokens [B, T, N, D], act_frames int [B, Q] -> GMM [B, Q, M, A]

The `Policy` class at the end is the stateful closed-loop controller that wraps the frozen encoder and this net.
"""
import dataclasses
from typing import Any, Callable, NamedTuple, Optional, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from roboshape import ranges
from roboshape.errors import UserError
from roboshape.models import encoder as encoder_lib
from roboshape.models import heads


class Block(nn.Module):
  """A pre-LayerNorm transformer block: masked self-attention, then an MLP.

  x [B, L, W], mask [B, 1, L, L] -> [B, L - first_query, W]: only tokens first_query.. are updated and returned
  (the trunk's last block updates the [ACT] tokens alone, the only outputs it reads).
  """
  num_heads: int
  mlp_ratio: int = 4
  dropout: float = 0.1

  @nn.compact
  def __call__(self, x, mask, train: bool, first_query: int = 0):
    width = x.shape[-1]
    h = nn.LayerNorm(name="ln_attn")(x)
    h = nn.MultiHeadDotProductAttention(num_heads=self.num_heads, dropout_rate=self.dropout,
                                        deterministic=not train, name="attn")(
                                            h[:, first_query:], h, mask=mask[:, :, first_query:])
    x = x[:, first_query:] + nn.Dropout(self.dropout, deterministic=not train)(h)
    h = nn.LayerNorm(name="ln_mlp")(x)
    h = nn.Dense(self.mlp_ratio * width, name="mlp_in")(h)
    h = nn.Dense(width, name="mlp_out")(nn.gelu(h))
    return x + nn.Dropout(self.dropout, deterministic=not train)(h)


def attention_mask(num_frames: int, num_tokens: int, act_frames: jax.Array,
                   present: Optional[jax.Array] = None) -> jax.Array:
  """The trunk's boolean mask [B, 1, L, L], L = T*N + Q (see the module docstring); act_frames int [B, Q].

  present: None, or bool [B, T*N], False for the observation tokens no token may attend to (all-zero padding). Such
  a key is masked in every row but its own, so every row keeps at least one key (itself; an [ACT] token always sees
  itself). With `present` None or all True the mask is the plain one above.
  """
  batch, q = act_frames.shape
  obs_frame = jnp.repeat(jnp.arange(num_frames), num_tokens)                   # [T*N]
  obs_frame = jnp.broadcast_to(obs_frame, (batch, obs_frame.shape[0]))
  obs_obs = obs_frame[:, None, :] <= obs_frame[:, :, None]                     # [B, TN, TN]
  obs_act = jnp.zeros((batch, obs_frame.shape[1], q), bool)                     # [B, TN, Q]
  act_obs = obs_frame[:, None, :] <= act_frames[:, :, None]                    # [B, Q, TN]
  act_act = jnp.broadcast_to(jnp.eye(q, dtype=bool), (batch, q, q))            # [B, Q, Q]
  mask = jnp.concatenate([jnp.concatenate([obs_obs, obs_act], -1), jnp.concatenate([act_obs, act_act], -1)], 1)
  if present is not None:
    keys = jnp.concatenate([present, jnp.ones((batch, q), bool)], axis=1)     # [B, L]
    mask = (mask & keys[:, None, :]) | jnp.eye(mask.shape[-1], dtype=bool)
  return mask[:, None]


class FramePool(nn.Module):
  """One frame's tokens [F, N, W] (F frames of a batch, `present` bool [F, N]: False for padding) -> [F, W]: a
  transformer block among the frame's present tokens, then attention from a learned query over them."""
  num_heads: int
  mlp_ratio: int = 4
  dropout: float = 0.1

  @nn.compact
  def __call__(self, x, present, train: bool):
    f, n, width = x.shape
    mask = (present[:, None, None, :] | jnp.eye(n, dtype=bool)[None, None])          # [F, 1, N, N]
    x = Block(self.num_heads, self.mlp_ratio, self.dropout, name="block")(x, mask, train)
    query = self.param("query", nn.initializers.normal(0.02), (1, 1, width))
    pooled = nn.MultiHeadDotProductAttention(num_heads=self.num_heads, dropout_rate=self.dropout,
                                             deterministic=not train, name="pool")(
                                                 jnp.broadcast_to(query, (f, 1, width)), nn.LayerNorm(name="ln")(x),
                                                 mask=present[:, None, None, :])
    return pooled[:, 0]


class Trunk(nn.Module):
  """tokens [B, T, N, D] float, act_frames int [B, Q] in [0, T) -> [ACT] outputs [B, Q, width].

  A token that is all exactly zero is padding (an absent object): it is masked out as an attention key (see
  `attention_mask`), so appending all-zero tokens to a frame leaves the [ACT] outputs unchanged.

  Attributes:
    width, num_layers, num_heads, mlp_ratio, dropout: the transformer encoder.
    max_history: H, the number of learned time embeddings (T <= H).
    frame_pool: each frame's N tokens first go through one attention block among themselves (padding masked) and
      are pooled into one token by attention from a learned query (`FramePool`), so the temporal transformer sees
      T tokens instead of T*N: per sample about N times cheaper, as a policy with one token per view is. The pool is
      permutation-invariant, so a frame's tokens still have no order.
  """
  width: int = 256
  num_layers: int = 8
  num_heads: int = 4
  mlp_ratio: int = 4
  dropout: float = 0.1
  max_history: int = 10
  frame_pool: bool = False

  @nn.compact
  def __call__(self, tokens: jax.Array, act_frames: jax.Array, train: bool = False) -> jax.Array:
    b, t, n, _ = tokens.shape
    if t > self.max_history:
      raise ValueError(f"a window of {t} frames is longer than the {self.max_history} time embeddings")
    init = nn.initializers.normal(0.02)
    time_emb = self.param("time_embedding", init, (self.max_history, self.width))
    act_token = self.param("act_token", init, (self.width,))
    present = jnp.any(tokens != 0, axis=-1).reshape(b, t * n)               # all-zero tokens: padding
    x = nn.Dense(self.width, name="token_proj")(tokens.astype(jnp.float32))
    if self.frame_pool:
      x = FramePool(self.num_heads, self.mlp_ratio, self.dropout, name="frame_pool")(
          x.reshape(b * t, n, self.width), present.reshape(b * t, n), train).reshape(b, t, 1, self.width)
      n, present = 1, jnp.ones((b, t), bool)
    x = x + time_emb[:t, None, :]
    x = x.reshape(b, t * n, self.width)
    act = act_token + time_emb[act_frames]                                     # [B, Q, W]
    x = jnp.concatenate([x, act], axis=1)
    x = nn.Dropout(self.dropout, deterministic=not train)(x)
    mask = attention_mask(t, n, act_frames, present)
    for i in range(self.num_layers):
      last = i == self.num_layers - 1
      x = Block(self.num_heads, self.mlp_ratio, self.dropout, name=f"block_{i}")(
          x, mask, train, first_query=t * n if last else 0)
    return nn.LayerNorm(name="ln_out")(x)


class PolicyNet(nn.Module):
  """The trunk followed by the GMM head: tokens [B, T, N, D], act_frames [B, Q] -> GMM with [B, Q, M, A] leaves."""
  width: int = 256
  num_layers: int = 8
  num_heads: int = 4
  mlp_ratio: int = 4
  dropout: float = 0.1
  max_history: int = 10
  action_dim: int = 7
  num_modes: int = 5
  min_scale: float = 1e-4
  frame_pool: bool = False

  @nn.compact
  def __call__(self, tokens, act_frames, train: bool = False) -> heads.GMM:
    h = Trunk(self.width, self.num_layers, self.num_heads, self.mlp_ratio, self.dropout, self.max_history,
              self.frame_pool, name="trunk")(tokens, act_frames, train)
    return heads.GMMHead(self.action_dim, self.num_modes, min_scale=self.min_scale, hidden=self.width, name="head")(h)


def net_from_config(policy_config) -> PolicyNet:
  """The PolicyNet a `config.policy` section describes."""
  c = policy_config
  return PolicyNet(width=c.width, num_layers=c.num_layers, num_heads=c.num_heads, mlp_ratio=c.mlp_ratio,
                   dropout=c.dropout, max_history=c.history, action_dim=c.action_dim, num_modes=c.num_modes,
                   min_scale=c.min_scale, frame_pool=bool(c.frame_pool))


# ----------------------------------------------------------------------------------------------------------------
# Closed-loop control: the frozen encoder's state and the token history, carried between steps.


class Carry(NamedTuple):
  """What the controller keeps between steps, for a batch of B environments.

  Attributes:
    enc_state: the encoder's recurrent state (every leaf with a leading batch axis B).
    history: [B, H, N, D] tokens of the last frames, oldest first; rows >= count are unused.
    count: int32 [B], frames seen since the env's reset.
    rng: [B, 2] one PRNG key per env for sampled actions, set at the env's reset from the policy's seed and the
      episode's seed, so an episode's sampled actions depend on nothing else (not on which envs share its batch,
      nor on what ran before it: an evaluation resumed after a kill repeats them).
  """
  enc_state: Any
  history: jax.Array
  count: jax.Array
  rng: jax.Array


ACTIONS = ("mean", "sample")      # ControlSpec.action: the mixture mean, or a mode drawn by weight

# The ranges of the policy section's fields that describe the trunk and how it acts (its training's: train/bc.py).
RANGES = (
    ranges.Int("policy.history", 1, "frames the policy sees"),
    ranges.Int("policy.width", 1, "the transformer's width"),
    ranges.Int("policy.num_layers", 1, "transformer blocks"),
    ranges.Int("policy.num_heads", 1, "attention heads, a divisor of policy.width"),
    ranges.Int("policy.mlp_ratio", 1, "the MLP's width over policy.width"),
    ranges.Int("policy.action_dim", 1, "action dimensions, 7 for the RoboShape envs"),
    ranges.Int("policy.num_modes", 1, "GMM modes"),
    ranges.Int("policy.eval.history", 0, "frames seen at control time; 0: policy.history"),
    ranges.Number("policy.dropout", 0.0, "a dropout probability", high=1.0),
    ranges.Number("policy.min_scale", 0.0, "the floor on the GMM's scales"),
    ranges.Number("policy.eval.noise", 0.0, "the sampling noise, a fraction of the mode's scale"),
    ranges.Flag("policy.proprio", "a proprioception token per frame"),
    ranges.Flag("policy.hand_relative", "each token's object relative to the hand (needs policy.proprio)"),
    ranges.Flag("policy.frame_pool", "each frame's tokens pooled into one before the temporal transformer"),
    ranges.Choice("policy.eval.action", ACTIONS, "the mixture mean, or a sampled mode"),
)


def check_config(config) -> None:
  """Raises UserError for the first bad field of the policy trunk and its control step: RANGES, heads that divide
  the width, a control-time history within the training one (roboshape/config_check.py runs it before any stage)."""
  ranges.check(config, RANGES)
  policy = config.policy
  if policy.width % policy.num_heads:
    raise UserError(f"policy.num_heads={policy.num_heads} does not divide policy.width={policy.width}: use a "
                    "divisor of the width.")
  if policy.eval.history > policy.history:
    raise UserError(f"policy.eval.history={policy.eval.history} exceeds policy.history={policy.history}: use at "
                    "most the training history (0: the training history).")


@dataclasses.dataclass(frozen=True)
class ControlSpec:
  """Static settings of the control step.

  Attributes:
    history: frames the trunk sees at control time (<= the training history).
    action: "mean" (mixture mean) or "sample" (a mode drawn by weight plus `noise` x its scale).
    noise: the sampling noise scale, for action="sample".
  """
  history: int
  action: str = "mean"
  noise: float = 0.1


def control_step(net: PolicyNet, spec: ControlSpec, encoder_step: Callable, norm_scale, norm_offset,
                 params, enc_params, carry: Carry, frames: jax.Array):
  """One control step, pure: frames uint8 [B, H, W, 3] -> (actions float32 [B, A] in env units, new carry)."""
  tokens, enc_state = encoder_step(enc_params, carry.enc_state, frames)            # [B, N, D]
  b, h = carry.history.shape[:2]
  full = (carry.count >= h)[:, None, None, None]
  history = jnp.where(full, jnp.roll(carry.history, -1, axis=1), carry.history)
  slot = jnp.minimum(carry.count, h - 1)                                            # [B]
  history = history.at[jnp.arange(b), slot].set(tokens.astype(history.dtype))
  gmm = net.apply(params, history, slot[:, None], train=False)
  gmm = jax.tree.map(lambda v: v[:, 0], gmm)                                        # [B, M, A] leaves
  keys = jax.vmap(jax.random.split)(carry.rng)                                      # [B, 2, 2]
  rng = keys[:, 0]
  if spec.action == "mean":
    action = heads.gmm_mean(gmm)                                                    # [B, A]
  else:
    action = jax.vmap(lambda g, k: heads.gmm_sample(g, k, spec.noise))(gmm, keys[:, 1])
  action = action * norm_scale + norm_offset
  return action.astype(jnp.float32), Carry(enc_state, history, carry.count + 1, rng)


class Policy:
  """A trained policy for closed-loop control: frame in, action out; the encoder state and history live inside.

    policy.reset(batch_size=1)
    action = policy.act(frame)            # uint8 [H, W, 3] -> float32 [7]
    actions = policy.act_batch(frames)    # uint8 [B, H, W, 3] -> float32 [B, 7]
    policy.reset_slots([2, 5])            # envs 2 and 5 of the batch start a new episode

  One jitted step serves every call of a batch size (`num_traces` counts the traces, i.e. compilations).
  """

  def __init__(self, net: PolicyNet, params, encoder, spec: ControlSpec, norm_scale, norm_offset, seed: int = 0,
               token_dtype=jnp.float32):
    if spec.history > net.max_history:
      raise ValueError(f"control history {spec.history} exceeds the training history {net.max_history}")
    if spec.action not in ACTIONS:
      raise ValueError(f"unknown action mode {spec.action!r}: use one of {ACTIONS}")
    self.net, self.params, self.encoder, self.spec = net, params, encoder, spec
    self._norm = (jnp.asarray(norm_scale, jnp.float32), jnp.asarray(norm_offset, jnp.float32))
    self._seed = seed
    self._token_dtype = token_dtype
    self.num_traces = 0
    self.carry: Optional[Carry] = None

    def step(params, enc_params, carry, frames):
      self.num_traces += 1  # runs only while jax traces, i.e. once per compilation
      return control_step(net, spec, encoder.step, self._norm[0], self._norm[1], params, enc_params, carry, frames)
    self._step = jax.jit(step)
    self.reset(1)

  @property
  def batch_size(self) -> int:
    return self.carry.count.shape[0]

  def _fresh(self, batch_size: int, seeds=None) -> Carry:
    """A new carry, on the default device: an encoder whose init_state is sharded otherwise (e.g. over a
    one-device mesh) would make the second step see another input sharding than the first, and recompile.
    `seeds` [batch_size]: each episode's seed, for its sampling key (default: the env's index in the batch)."""
    enc = self.encoder
    seeds = np.arange(batch_size) if seeds is None else np.asarray(seeds)
    keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(jax.random.PRNGKey(self._seed),
                                                           jnp.asarray(seeds % 2**32, jnp.uint32))
    return jax.device_put(Carry(
        enc_state=enc.init_state(batch_size),
        history=jnp.zeros((batch_size, self.spec.history, enc.num_tokens, enc.token_dim), self._token_dtype),
        count=jnp.zeros((batch_size,), jnp.int32),
        rng=keys), jax.devices()[0])

  def reset(self, batch_size: int = 1, seeds: Optional[Sequence[int]] = None) -> None:
    """Starts new episodes in all `batch_size` environments; `seeds` (one per env, e.g. the env seeds) key their
    sampled actions (action="sample"), by default the env's index."""
    self.carry = self._fresh(batch_size, seeds)

  def reset_slots(self, indices: Sequence[int], seeds: Optional[Sequence[int]] = None) -> None:
    """Starts a new episode in the environments `indices` of the batch (with `seeds`, one per index, keying their
    sampled actions; by default the env's index); the others keep their memory."""
    b = self.batch_size
    indices = np.asarray(indices, int)
    mask = np.zeros((b,), bool)
    mask[indices] = True
    episode_seeds = np.arange(b)
    if seeds is not None:
      episode_seeds[indices] = np.asarray(seeds, np.int64)
    fresh = self._fresh(b, episode_seeds)
    def pick(new, old):
      if not hasattr(old, "shape") or old.ndim == 0 or old.shape[0] != b:
        return old
      return jnp.where(mask.reshape((b,) + (1,) * (old.ndim - 1)), new, old)
    self.carry = jax.tree.map(pick, fresh, self.carry)

  @property
  def inputs(self):
    """The observation keys the encoder reads (roboshape.encoders.OBSERVATION_KEYS)."""
    return self.encoder.inputs

  def act_batch(self, frames) -> np.ndarray:
    """uint8 [B, H, W, 3] (or a dict of [B, ...] observations holding the encoder's inputs) -> float32 [B, A];
    B must equal the batch size of the last reset."""
    frames = jax.tree.map(jnp.asarray, encoder_lib.select(self.encoder.inputs, frames))
    batch = jax.tree.leaves(frames)[0].shape[0]
    if batch != self.batch_size:
      raise ValueError(f"got {batch} frames for a policy reset with batch_size={self.batch_size}")
    actions, self.carry = self._step(self.params, self.encoder.params, self.carry, frames)
    return np.asarray(actions)

  def act(self, frame) -> np.ndarray:
    """uint8 [H, W, 3] (or a dict of observations) -> float32 [A], for a policy reset with batch_size=1."""
    return self.act_batch(jax.tree.map(lambda x: np.asarray(x)[None], frame))[0]
