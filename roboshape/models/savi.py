"""SAVi: slot attention for video, the object-centric encoder that roboshape pretrains by reconstruction.

Per frame t, a CNN turns the image into a set of N features; slot attention (the corrector) refines the K slots
predicted from frame t-1 against those features; a transformer block (the predictor) maps the corrected slots to
the initial slots of frame t+1; a spatial-broadcast decoder reconstructs the frame from the corrected slots, with
per-slot RGB and alpha masks normalised over the slots. The first frame starts from slots drawn from a learned
Gaussian.

  model = model_from_config(config)       # or build_model(config.savi, resolution, depth)
  out = model.apply({"params": params}, video, rngs={"slots": key})   # video float [B, T, H, W, 3] in [0, 1]
  out["slots"] [B, T, K, D], out["recon"] [B, T, H, W, 3], out["masks"] [B, T, K, H, W], out["rgb"] [B, T, K, H, W, 3]

  slots, state = model.apply({"params": params}, frame, state, method=SAVi.step)   # one frame of it

Inference, as the frozen encoder and the evaluators run it (pure functions of the model and its params):

  out = decompose(model, params, video)         # video uint8 [B, T, H, W, 3], from the deterministic first slots
  slots, state = frozen_step(model, params, state, frames)    # frames uint8 [B, H, W, 3]; state [B, K, D]

Every size and mode comes from the config (configs/common.py:savi_config holds the defaults; `build_model` reads
them, `check_config` checks them against the frames).
"""
import functools
import math
from typing import Dict, Optional, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from roboshape.errors import UserError
from roboshape.models import layers

INIT_MEANS = ("shared", "queries", "cues")       # SlotInitializer(mean=...)
# A conditional SAVi's cue of one object in the first frame (first_frame_cues): whether it is there, and its box's
# top, left, bottom and right pixel centres in [-1, 1] (row 0 at the top), as SAVi conditions on boxes.
CUE_FIELDS = ("present", "top", "left", "bottom", "right")
SLOT_GRADIENTS = ("full", "last")                # SlotAttention(gradient=...)
DECODER_RGBS = ("spatial", "slot")               # SpatialBroadcastDecoder(rgb=...)
DECODER_POSITIONS = ("coords", "learned")        # SpatialBroadcastDecoder(position=...)
UPSAMPLINGS = ("subpixel", "transpose")          # Upsample(mode=...)
INIT_SLOTS_SEED = 0                              # the fixed key of the frozen encoder's first-frame slots


class CNNEncoder(nn.Module):
  """Convolutions with ReLU, a position embedding, then a per-location MLP.

  images [B, H, W, 3] -> features [B, N, F] with N = (H / prod(strides)) * (W / prod(strides)).
  """
  features: Sequence[int]
  kernel_size: int
  strides: Sequence[int]
  mlp_size: int
  output_size: int

  @nn.compact
  def __call__(self, images: jnp.ndarray) -> jnp.ndarray:
    x = images
    for i, (channels, stride) in enumerate(zip(self.features, self.strides)):
      x = nn.Conv(channels, (self.kernel_size, self.kernel_size), strides=(stride, stride), padding="SAME",
                  name=f"conv{i}")(x)
      x = nn.relu(x)
    x = layers.PositionEmbedding(name="position")(x)
    x = x.reshape(x.shape[0], -1, x.shape[-1])
    return layers.MLP(self.mlp_size, self.output_size, layernorm=True, name="mlp")(x)


class SlotInitializer(nn.Module):
  """K first-frame slots: drawn from a learned diagonal Gaussian, K learned vectors, or encoded from cues.

  mean="shared": one mean [D] and log-scale [D] for all slots, so only the noise tells the slots apart (the Slot
  Attention paper's initialisation). mean="queries": K learned vectors and no noise at all (learned queries): every
  episode starts from the same slots, so a slot can come to stand for a part of the scene that is always there (the
  robot, the table). mean="cues": conditional SAVi, slot k encoded by an MLP from the cue of object k in the first
  frame (first_frame_cues: its box, or "absent"), so each slot starts on its object and the noise is not used.
  """
  num_slots: int
  slot_size: int
  mean: str

  @nn.compact
  def __call__(self, noise: jnp.ndarray, cues: Optional[jnp.ndarray] = None) -> jnp.ndarray:
    """noise [..., K, D] standard normal (and for "cues" the cues [..., K, len(CUE_FIELDS)]) -> slots [..., K, D] =
    mean + exp(log_scale) * noise (= mean, "queries"; = MLP(cues), "cues")."""
    if self.mean not in INIT_MEANS:
      raise ValueError(f"unknown slot initialisation mean {self.mean!r}; use one of {INIT_MEANS}.")
    if self.mean == "cues":
      if cues is None:
        raise ValueError("a conditional SAVi (savi.init_mean='cues') starts from the first frame's cues: pass them.")
      return layers.MLP(2 * self.slot_size, self.slot_size, name="cues")(cues)
    shape = (self.slot_size,) if self.mean == "shared" else (self.num_slots, self.slot_size)
    mean = self.param("mean", nn.initializers.normal(1.0), shape)
    if self.mean == "queries":
      return jnp.broadcast_to(mean, noise.shape)
    log_scale = self.param("log_scale", nn.initializers.zeros, (self.slot_size,))
    return mean + jnp.exp(log_scale) * noise


class FullGrid(nn.Module):
  """Slot attention's inputs on the frame's own pixel grid rather than the CNN's coarser one: every pixel gets the
  features of the encoder cell it lies in (nearest upsampling) plus a linear map of one convolution of the full-
  resolution frame around it, with a position embedding (so the pixels of one cell differ by colour and place).
  The CNN still sees the pooled frames and carries the context; this path adds what the pooling and strides lose,
  at the cost of one convolution of `channels` per pixel (and slot attention over H x W inputs, cheap on the slots'
  side: SlotAttention).

  frame [B, H, W, 3] in [0, 1], features [B, g * g, F] on the encoder's g x g grid (g divides H) -> [B, H * W, F].
  """
  channels: int
  kernel_size: int

  @nn.compact
  def __call__(self, frame: jnp.ndarray, features: jnp.ndarray) -> jnp.ndarray:
    batch, height, width, _ = frame.shape
    grid, size = math.isqrt(features.shape[1]), features.shape[-1]
    cells = features.reshape(batch, grid, 1, grid, 1, size)
    coarse = jnp.broadcast_to(cells, (batch, grid, height // grid, grid, width // grid, size))
    x = nn.Conv(self.channels, (self.kernel_size, self.kernel_size), padding="SAME", name="conv")(frame)
    x = layers.PositionEmbedding(name="position")(nn.relu(x))
    fine = nn.Dense(size, name="project")(x.reshape(batch, height * width, self.channels))
    return coarse.reshape(batch, height * width, size) + fine


class _Kernel(nn.Module):
  """A bias-free Dense layer's kernel [in_size, out_size] on its own (param "kernel", Dense's default init), for
  applying the map where it is cheapest (SlotAttention)."""
  in_size: int
  out_size: int

  @nn.compact
  def __call__(self) -> jnp.ndarray:
    return self.param("kernel", nn.initializers.lecun_normal(), (self.in_size, self.out_size))


class SlotAttention(nn.Module):
  """Iterative slot attention: attention normalised over the slots (they compete for each input), a weighted mean
  of the values per slot, a GRU update and a residual MLP (none with mlp_size=0, as SAVi-S's corrector).

  gradient="full": back-propagation runs through every iteration. gradient="last": the first-order implicit
  gradient (the iterations approximate a fixed point): all but the last iteration run under stop_gradient, and the
  initial slots get the last iteration's gradient straight through (slots' = sg(slots) + init - sg(init)), so the
  learned initial slots (and SAVi's predictor) still train; the backward pass is one iteration long.

  The keys and values are linear maps of the inputs (kernels "key" and "value", [F, D]), applied on the slots' side:
  a slot's logits are its query mapped back through the key kernel against the inputs, q . (x W_k) = (q W_k^T) . x,
  and its update the value kernel applied to its weighted mean of the inputs, w . (x W_v) = (w . x) W_v. The same
  numbers as projecting every input, but an iteration costs K x N x F instead of N x F x D for the projections,
  which is what makes slot attention on a full-resolution grid (thousands of inputs) cheap.
  slots [B, K, D], inputs [B, N, F] -> slots [B, K, D]; equivariant to permutations of the K slots.
  """
  num_iterations: int
  mlp_size: int
  gradient: str = "full"
  epsilon: float = 1e-8

  @nn.compact
  def __call__(self, slots: jnp.ndarray, inputs: jnp.ndarray) -> jnp.ndarray:
    if self.gradient not in SLOT_GRADIENTS:
      raise ValueError(f"unknown slot-attention gradient {self.gradient!r}; use one of {SLOT_GRADIENTS}.")
    slot_size, init = slots.shape[-1], slots
    inputs = nn.LayerNorm(name="norm_inputs")(inputs)                     # [B, N, F]
    key_kernel = _Kernel(inputs.shape[-1], slot_size, name="key")()        # [F, D]
    value_kernel = _Kernel(inputs.shape[-1], slot_size, name="value")()    # [F, D]
    query_dense = nn.Dense(slot_size, use_bias=False, name="query")
    norm_slots = nn.LayerNorm(name="norm_slots")
    gru = nn.GRUCell(slot_size, name="gru")
    mlp = layers.MLP(self.mlp_size, slot_size, layernorm=True, residual=True, name="mlp") if self.mlp_size else None
    iterations = self.num_iterations
    for i in range(iterations):
      if self.gradient == "last" and i == iterations - 1 and i > 0:
        slots = jax.lax.stop_gradient(slots) + init - jax.lax.stop_gradient(init)
      queries = query_dense(norm_slots(slots)) / math.sqrt(slot_size)     # [B, K, D]
      logits = jnp.einsum("bkf,bnf->bkn", queries @ key_kernel.T, inputs)  # [B, K, N] = queries . keys
      attention = jax.nn.softmax(logits, axis=1)                          # over the slots
      self.sow("intermediates", "attention", attention)                   # kept only when asked for (mutable)
      weights = attention / (attention.sum(axis=-1, keepdims=True) + self.epsilon)
      updates = jnp.einsum("bkn,bnf->bkf", weights, inputs) @ value_kernel  # weighted mean of the values, [B, K, D]
      slots, _ = gru(slots, updates)
      if mlp is not None:
        slots = mlp(slots)
    return slots


class Processor(nn.Module):
  """One frame of the recurrence: corrector (slot attention) then predictor (a transformer block over the slots).

  (predicted [B, K, D], features [B, N, F]) -> (corrected [B, K, D], next predicted [B, K, D])
  """
  num_iterations: int
  slot_mlp_size: int
  predictor_heads: int
  predictor_mlp_size: int
  predictor_identity_init: bool
  gradient: str

  def setup(self):
    self.corrector = SlotAttention(self.num_iterations, self.slot_mlp_size, gradient=self.gradient)
    self.predictor = layers.TransformerBlock(self.predictor_heads, self.predictor_mlp_size, self.predictor_identity_init)

  def __call__(self, predicted: jnp.ndarray, features: jnp.ndarray) -> Tuple[jnp.ndarray, jnp.ndarray]:
    corrected = self.corrector(predicted, features)
    return corrected, self.predictor(corrected)


class Upsample(nn.Module):
  """A learned upsampling by `stride` (a plain convolution when stride is 1, a Dense layer when the kernel is 1x1).

  "subpixel": a convolution to stride * stride * C channels, then depth-to-space; "transpose": a transposed
  convolution. Both learn the same family of upsamplings; XLA's CPU backend runs the sub-pixel form several times
  faster (results/small/README.md), GPUs run both well.
  x [B, H, W, C_in] -> [B, H * stride, W * stride, features]
  """
  features: int
  kernel_size: int
  stride: int
  mode: str = "subpixel"

  @nn.compact
  def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
    kernel, s = (self.kernel_size, self.kernel_size), self.stride
    if s == 1 and self.kernel_size == 1:
      return nn.Dense(self.features, name="conv")(x)                     # a 1x1 conv: XLA's CPU convs are slow
    if s == 1:
      return nn.Conv(self.features, kernel, padding="SAME", name="conv")(x)
    if self.mode == "transpose":
      return nn.ConvTranspose(self.features, kernel, strides=(s, s), padding="SAME", name="conv")(x)
    if self.mode != "subpixel":
      raise ValueError(f"unknown upsampling {self.mode!r}; use one of {UPSAMPLINGS}.")
    y = nn.Conv(self.features * s * s, kernel, padding="SAME", name="conv")(x)
    b, h, w, _ = y.shape
    y = y.reshape(b, h, w, s, s, self.features).transpose(0, 1, 3, 2, 4, 5)
    return y.reshape(b, h * s, w * s, self.features)


class SpatialBroadcastDecoder(nn.Module):
  """Decodes every slot on its own into RGB and an alpha logit; masks are the softmax of the alphas over slots.

  A learned position embedding is added to each slot broadcast over a grid_size x grid_size grid, then each layer
  upsamples by its stride (see Upsample), with ReLU; a final 1x1 layer gives RGB and alpha (rgb="spatial"), or
  alpha only, with each slot painted in one colour, a linear map of the slot (rgb="slot": a slot can then explain
  only a region of one colour, which pushes the masks to follow colours).

  position="coords": the grid's position embedding is a learned linear map of the pixel coordinates (SAVi's), so the
  first layer sees a ramp per channel and a shallow decoder draws smooth, convex-ish masks. position="learned": a
  free learned vector per grid cell; with a full-resolution grid and 1x1 layers (kernel_size=1, strides all 1) the
  decoder is a per-pixel MLP of (slot, cell), which can draw a mask of any shape (e.g. a robot arm) at little cost.

  depth=True: every slot also gives a depth per pixel (a 1x1 layer on the CNN's features, free of the colour
  mode), mixed by the same masks into depth [B, H, W] (SAVi++'s depth target: a cue other than colour, e.g. the
  white robot stands out of the white table).

  slots [B, K, D] -> dict(recon [B, H, W, 3], rgb [B, K, H, W, 3], masks [B, K, H, W]) (and depth [B, H, W],
  slot_depth [B, K, H, W] with depth=True), with H = W = grid_size * prod(strides).
  """
  grid_size: int
  features: Sequence[int]
  kernel_size: int
  strides: Sequence[int]
  upsampling: str = "subpixel"
  rgb: str = "spatial"
  position: str = "coords"
  depth: bool = False

  @nn.compact
  def __call__(self, slots: jnp.ndarray) -> Dict[str, jnp.ndarray]:
    batch, num_slots, slot_size = slots.shape
    grid = (self.grid_size, self.grid_size)
    if self.position == "coords":
      x = jnp.broadcast_to(slots.reshape(batch * num_slots, 1, 1, slot_size), (batch * num_slots, *grid, slot_size))
      x = layers.PositionEmbedding(name="position")(x)
    elif self.position == "learned":                                       # the slot projected, then broadcast
      width = self.features[0] if self.features else slot_size
      x = nn.Dense(width, name="project")(slots).reshape(batch * num_slots, 1, 1, width)
      x = x + self.param("position", nn.initializers.normal(0.5), (*grid, width))
    else:
      raise ValueError(f"unknown decoder position {self.position!r}; use one of {DECODER_POSITIONS}.")
    for i, (channels, stride) in enumerate(zip(self.features, self.strides)):
      x = nn.relu(Upsample(channels, self.kernel_size, stride, self.upsampling, name=f"up{i}")(x))
    out = {}
    if self.depth:
      out["slot_depth"] = nn.Dense(1, name="depth")(x)[..., 0].reshape(batch, num_slots, *x.shape[1:3])
    if self.rgb == "spatial":
      x = nn.Dense(4, name="output")(x)                                    # [B*K, H, W, 4]
      x = x.reshape(batch, num_slots, *x.shape[1:])
      rgb, alpha = x[..., :3], x[..., 3]
    elif self.rgb == "slot":
      alpha = nn.Dense(1, name="output")(x)[..., 0].reshape(batch, num_slots, *x.shape[1:3])
      colour = nn.Dense(3, name="colour")(slots)                           # [B, K, 3]
      rgb = jnp.broadcast_to(colour[:, :, None, None, :], (*alpha.shape, 3))
    else:
      raise ValueError(f"unknown decoder rgb {self.rgb!r}; use one of {DECODER_RGBS}.")
    masks = jax.nn.softmax(alpha, axis=1)                                  # [B, K, H, W], sums to 1 over K
    recon = jnp.sum(masks[..., None] * rgb, axis=1)                        # [B, H, W, 3]
    if self.depth:
      out["depth"] = jnp.sum(masks * out["slot_depth"], axis=1)            # [B, H, W]
    return {**out, "recon": recon, "rgb": rgb, "masks": masks}


def pool_frames(frames: jnp.ndarray, factor: int) -> jnp.ndarray:
  """Average-pools frames [..., H, W, C] by `factor` in both directions -> [..., H / factor, W / factor, C]."""
  if factor == 1:
    return frames
  *lead, h, w, c = frames.shape
  return frames.reshape(*lead, h // factor, factor, w // factor, factor, c).mean(axis=(-4, -2))


def _fold_time(x: jnp.ndarray) -> jnp.ndarray:
  return x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])


def _unfold_time(x: jnp.ndarray, batch: int) -> jnp.ndarray:
  return x.reshape(batch, x.shape[0] // batch, *x.shape[1:])


class SAVi(nn.Module):
  """The SAVi video model: CNN encoder, slot initializer, corrector + predictor scanned over time, decoder.

  Frames are float in [0, 1]. The model's rng stream "slots" draws the initial slots when none are given.
  Slot attention runs num_iterations times on every frame: on the first from the initial slots, on every later one
  from the predictor's slots. Every field is required: `build_model` sets them from a config.
  With input_pool = f > 1 the frames are average-pooled by f before the encoder and the decoder reconstructs the
  pooled frames (a cheaper model of the same frames; the masks are 1/f of the frames' resolution).
  """
  num_slots: int
  slot_size: int
  init_mean: str
  num_iterations: int
  slot_gradient: str
  slot_mlp_size: int
  encoder_features: Sequence[int]
  encoder_kernel_size: int
  encoder_strides: Sequence[int]
  encoder_mlp_size: int
  feature_size: int
  predictor_heads: int
  predictor_mlp_size: int
  predictor_identity_init: bool
  decoder_grid_size: int
  decoder_features: Sequence[int]
  decoder_kernel_size: int
  decoder_strides: Sequence[int]
  decoder_upsampling: str
  decoder_rgb: str
  decoder_position: str
  decoder_depth: bool
  input_pool: int
  full_grid: int

  def setup(self):
    self.encoder = CNNEncoder(self.encoder_features, self.encoder_kernel_size, self.encoder_strides,
                              self.encoder_mlp_size, self.feature_size)
    if self.full_grid:
      self.fine = FullGrid(self.full_grid, self.encoder_kernel_size)
    self.initializer = SlotInitializer(self.num_slots, self.slot_size, self.init_mean)
    self.processor = Processor(self.num_iterations, self.slot_mlp_size, self.predictor_heads,
                               self.predictor_mlp_size, self.predictor_identity_init, self.slot_gradient)
    self.decoder = SpatialBroadcastDecoder(self.decoder_grid_size, self.decoder_features, self.decoder_kernel_size,
                                           self.decoder_strides, self.decoder_upsampling, self.decoder_rgb,
                                           self.decoder_position, depth=self.decoder_depth)

  @property
  def output_resolution(self) -> int:
    return self.decoder_grid_size * math.prod(self.decoder_strides)

  def initial_slots(self, noise: jnp.ndarray, cues: Optional[jnp.ndarray] = None) -> jnp.ndarray:
    """noise [..., K, D] standard normal (cues [..., K, C] for a conditional SAVi) -> the first frame's slots
    [..., K, D] from the learned initializer."""
    return self.initializer(noise, cues)

  def decode(self, slots: jnp.ndarray) -> Dict[str, jnp.ndarray]:
    """slots [B, K, D] -> dict(recon [B, H, W, 3], rgb [B, K, H, W, 3], masks [B, K, H, W])."""
    return self.decoder(slots)

  def encode_frame(self, frame: jnp.ndarray) -> jnp.ndarray:
    """frame [B, H, W, 3] in [0, 1] -> slot attention's inputs [B, N, F]: the encoder's features of the pooled frame,
    on the frame's full H x W grid with full_grid > 0 (FullGrid)."""
    features = self.encoder(pool_frames(frame, self.input_pool))
    return self.fine(frame, features) if self.full_grid else features

  def step(self, frame: jnp.ndarray, state: jnp.ndarray) -> Tuple[jnp.ndarray, jnp.ndarray]:
    """One frame: (frame [B, H, W, 3] in [0, 1], predicted slots [B, K, D]) -> (slots [B, K, D], next state); on a
    video's first frame `state` is its initial slots."""
    return self.processor(state, self.encode_frame(frame))

  def __call__(self, video: jnp.ndarray, init_slots: Optional[jnp.ndarray] = None,
               decode: bool = True, cues: Optional[jnp.ndarray] = None) -> Dict[str, jnp.ndarray]:
    """video [B, T, H, W, 3] in [0, 1] (and optionally the first frame's slots [B, K, D], or for a conditional SAVi
    the first frame's cues [B, K, C] they are encoded from; initialisation may omit the cues) -> dict:

    slots [B, T, K, D] (corrected), predicted [B, T, K, D] (each frame's prediction for the next one), and when
    `decode`: recon [B, T, h, w, 3], rgb [B, T, K, h, w, 3], masks [B, T, K, h, w] with h = H / input_pool
    (and depth [B, T, h, w], slot_depth [B, T, K, h, w] with decoder_depth).
    """
    batch = video.shape[0]
    if init_slots is None:
      noise = jax.random.normal(self.make_rng("slots"), (batch, self.num_slots, self.slot_size))
      if cues is None and self.init_mean == "cues" and self.is_initializing():
        cues = jnp.zeros((batch, self.num_slots, len(CUE_FIELDS)), jnp.float32)     # shapes alone
      init_slots = self.initial_slots(noise, cues)
    features = _unfold_time(self.encode_frame(_fold_time(video)), batch)  # [B, T, N, F]

    def body(processor, carry, frame_features):
      corrected, predicted = processor(carry, frame_features)
      return predicted, (corrected, predicted)

    scan = nn.scan(body, variable_broadcast="params", variable_axes={"intermediates": 1}, split_rngs={"params": False},
                   in_axes=1, out_axes=1)
    _, (slots, predicted) = scan(self.processor, init_slots, features)
    out = {"slots": slots, "predicted": predicted}
    if decode:
      decoded = self.decoder(_fold_time(slots))
      out.update({k: _unfold_time(v, batch) for k, v in decoded.items()})
    return out


def input_pool(section) -> int:
  """The factor by which a frame model (SAVi's section, the AE's) average-pools the frames: its `pool` field."""
  return int(section.pool)


def depth_weight(config) -> float:
  """config.pretrain.train.depth_weight: the weight of the depth MSE in the pretraining loss; a model pretrained
  with a weight > 0 predicts depth (SAVi and the AE alike), so it is also built with a depth output to load."""
  return float(config.pretrain.train.depth_weight)


def decoder_grid_size(section, resolution: int) -> int:
  """The broadcast grid's side: the section's decoder.grid_size, or (resolution / pool) / prod(strides) when 0."""
  grid = int(section.decoder.grid_size)
  return grid if grid > 0 else resolution // input_pool(section) // math.prod(section.decoder.strides)


def check_frames(section, name: str, resolution: int) -> None:
  """Raises UserError, "<name>.<field>=<value>: use ...", unless the frame model of config section `name` (savi,
  ae: a pool, a CNN encoder and a spatial-broadcast decoder) models square frames of `resolution` pixels a side:
  known decoder modes, a pool that divides the frames, a decoder that draws the pooled frames' size."""
  c = section
  for field, value, choices in (("decoder.position", c.decoder.position, DECODER_POSITIONS),
                                ("decoder.upsampling", c.decoder.upsampling, UPSAMPLINGS)):
    if value not in choices:
      raise UserError(f"{name}.{field}={value!r}: use one of {', '.join(choices)} (see configs/common.py).")
  pool = input_pool(c)
  if pool < 1 or resolution % pool:
    raise UserError(f"{name}.pool={pool} does not divide env.resolution={resolution}: use a positive divisor of it.")
  out = decoder_grid_size(c, resolution) * math.prod(c.decoder.strides)
  if out != resolution // pool:
    raise UserError(f"{name}.decoder.grid_size={c.decoder.grid_size} with {name}.decoder.strides="
                    f"{tuple(c.decoder.strides)!r} makes {out}x{out} images, but the model draws "
                    f"{resolution // pool}x{resolution // pool} frames (env.resolution / {name}.pool): set "
                    f"{name}.decoder.grid_size=0 (automatic) or change {name}.decoder.strides.")


def check_config(savi_config, resolution: int) -> None:
  """Raises UserError, "savi.<field>=<value>: use ...", unless a `config.savi` section builds a SAVi that models
  square frames of `resolution` pixels a side: SAVi's own modes, then `check_frames`. (Its ranges are declared with
  the encoder, roboshape/encoders/savi.py.)"""
  c = savi_config
  for field, value, choices in (("init_mean", c.init_mean, INIT_MEANS),
                                ("slot_gradient", c.slot_gradient, SLOT_GRADIENTS),
                                ("decoder.rgb", c.decoder.rgb, DECODER_RGBS)):
    if value not in choices:
      raise UserError(f"savi.{field}={value!r}: use one of {', '.join(choices)} (see configs/common.py).")
  check_frames(c, "savi", resolution)
  grid = resolution // input_pool(c) // math.prod(c.encoder.strides)
  if c.full_grid and grid * input_pool(c) * math.prod(c.encoder.strides) != resolution:
    raise UserError(f"savi.full_grid={c.full_grid}: the CNN's {grid}x{grid} grid does not tile the "
                    f"{resolution}x{resolution} frame (savi.pool x prod(savi.encoder.strides) must divide "
                    f"env.resolution); set savi.full_grid=0 or change savi.pool or savi.encoder.strides.")


def parameter_count(savi_config, resolution: int) -> int:
  """The number of learned parameters (the sum of the params' leaf sizes) of the SAVi a `config.savi` section
  builds for frames of `resolution` pixels a side; from shapes alone (jax.eval_shape of init), so it costs no
  compute."""
  model = build_model(savi_config, resolution)
  video = jax.ShapeDtypeStruct((1, 1, resolution, resolution, 3), jnp.float32)
  shapes = jax.eval_shape(lambda v: model.init({"params": jax.random.key(0), "slots": jax.random.key(1)}, v), video)
  return sum(math.prod(leaf.shape) for leaf in jax.tree_util.tree_leaves(shapes["params"]))


def build_model(savi_config, resolution: int, depth: bool = False) -> SAVi:
  """The SAVi module a `config.savi` section describes (see configs/common.py:savi_config) for square frames of
  `resolution` pixels a side, with a depth output when `depth`."""
  c = savi_config
  return SAVi(
      num_slots=int(c.num_slots), slot_size=int(c.slot_size), init_mean=str(c.init_mean),
      num_iterations=int(c.num_iterations), slot_gradient=str(c.slot_gradient), slot_mlp_size=int(c.slot_mlp_size),
      encoder_features=tuple(c.encoder.features), encoder_kernel_size=int(c.encoder.kernel_size),
      encoder_strides=tuple(c.encoder.strides), encoder_mlp_size=int(c.encoder.mlp_size),
      feature_size=int(c.encoder.output_size),
      predictor_heads=int(c.predictor.num_heads), predictor_mlp_size=int(c.predictor.mlp_size),
      predictor_identity_init=bool(c.predictor.identity_init),
      decoder_grid_size=decoder_grid_size(c, resolution), decoder_features=tuple(c.decoder.features),
      decoder_kernel_size=int(c.decoder.kernel_size), decoder_strides=tuple(c.decoder.strides),
      decoder_upsampling=str(c.decoder.upsampling), decoder_rgb=str(c.decoder.rgb),
      decoder_position=str(c.decoder.position), decoder_depth=bool(depth),
      input_pool=input_pool(c), full_grid=int(c.full_grid))


def model_from_config(config) -> SAVi:
  """The SAVi of a run's config: its savi section, for frames of env.resolution, with a depth output when the
  pretraining weights depth (`depth_weight`)."""
  return build_model(config.savi, int(config.env.resolution), depth_weight(config) > 0)


# ----------------------------------------------------------------------------------------------------------------
# Inference: the frozen encoder's step and the decomposition the evaluators score.


def to_float(video: jax.Array) -> jax.Array:
  """uint8 frames [...] -> float32 in [0, 1], the models' input scaling."""
  return video.astype(jnp.float32) / 255.0


def conditional(model) -> bool:
  """Whether `model` is a conditional SAVi: its first slots come from the first frame's cues (init_mean "cues")."""
  return isinstance(model, SAVi) and model.init_mean == "cues"


def first_frame_cues(segmentation: jax.Array, num_slots: int) -> jax.Array:
  """A frame's object ids int [B, H, W] -> the cues of a conditional SAVi's first slots, float32 [B, K, C]: row k
  the cue of id k (CUE_FIELDS: 1 and its box's top, left, bottom, right pixel centres in [-1, 1]; all zero where
  id k is not in the frame). Ids >= K have no slot and no cue. The caller maps ids as the slots should see them
  (e.g. the hand onto the arm: the robot as one object)."""
  h, w = segmentation.shape[-2:]
  masks = jax.nn.one_hot(jnp.asarray(segmentation), num_slots, dtype=jnp.float32)   # [B, H, W, K]; ids >= K: none
  rows, cols = masks.max(axis=2), masks.max(axis=1)                                    # [B, H, K], [B, W, K]
  present = rows.max(axis=1)                                                           # [B, K]

  def extent(marginal, n):
    centres = ((2.0 * jnp.arange(n, dtype=jnp.float32) + 1.0) / n - 1.0)[None, :, None]
    return (jnp.min(jnp.where(marginal > 0, centres, 1.0), axis=1),
            jnp.max(jnp.where(marginal > 0, centres, -1.0), axis=1))

  (top, bottom), (left, right) = extent(rows, h), extent(cols, w)
  cues = jnp.stack([present, top, left, bottom, right], axis=-1)
  return jnp.where(present[..., None] > 0, cues, 0.0)


def initial_slots(model: SAVi, params, batch_size: int, cues: Optional[jax.Array] = None) -> jax.Array:
  """The frozen encoder's first-frame slots [B, K, D]: the learned initializer on noise drawn with the fixed key
  INIT_SLOTS_SEED, so encoding is deterministic and the same for every episode of a batch; a conditional SAVi's
  from each episode's `cues` [B, K, C] (first_frame_cues)."""
  if conditional(model):
    if cues is None:
      raise ValueError("a conditional SAVi's first slots come from the first frame's cues: pass them.")
    return model.apply({"params": params}, None, cues, method=SAVi.initial_slots)
  noise = jax.random.normal(jax.random.key(INIT_SLOTS_SEED), (model.num_slots, model.slot_size))
  slots = model.apply({"params": params}, noise, method=SAVi.initial_slots)
  return jnp.broadcast_to(slots, (batch_size, *slots.shape))


@functools.partial(jax.jit, static_argnums=0)
def decompose(model: SAVi, params, video: jax.Array, first_segmentation: Optional[jax.Array] = None
              ) -> Dict[str, jax.Array]:
  """video uint8 [B, T, H, W, 3] -> the model's outputs (slots, recon, rgb, masks, ...) from `initial_slots`; a
  conditional SAVi's from the cues of `first_segmentation` [B, H, W] (its first frame's ids, as the slots see
  them)."""
  cues = None if first_segmentation is None else first_frame_cues(first_segmentation, model.num_slots)
  return model.apply({"params": params}, to_float(video),
                     init_slots=initial_slots(model, params, video.shape[0], cues))


def frozen_step(model: SAVi, params, state: jax.Array, frames: jax.Array) -> Tuple[jax.Array, jax.Array]:
  """The FrozenEncoder step: (params, predicted slots [B, K, D], frames uint8 [B, H, W, 3]) -> (the frame's slots
  [B, K, D], the predicted slots of the next frame [B, K, D]); an episode's first state is `initial_slots`."""
  return model.apply({"params": params}, to_float(frames), state, method=SAVi.step)


# Entries a located step appends to each slot: where the slot attends in the frame and how far that is.
LOCATION_FIELDS = ("row", "col", "depth")
MIN_ATTENTION = 0.5   # a slot attending to less than this many feature cells in all is "nowhere" (no location)


def located_step(model: SAVi, params, state: jax.Array, frames: jax.Array,
                 depth: jax.Array) -> Tuple[jax.Array, jax.Array]:
  """`frozen_step` with each slot's location appended: (params, predicted slots [B, K, D], frames uint8 [B, H, W, 3],
  depth uint16 [B, H, W] millimetres) -> (tokens [B, K, D + 3], the next frame's predicted slots).

  The location of a slot is where its last slot-attention iteration attends on the feature grid: the attention-
  weighted mean of the cells' centres (row, col, in [-1, 1] of the frame, row 0 at the top, as the objects tokens'
  centroids) and of the camera depth averaged over each cell (metres). A slot whose attention adds up to less than
  MIN_ATTENTION cells gets zeros, which read as "no location". Nothing here knows which slot is which object.
  """
  (slots, predicted), variables = model.apply({"params": params}, to_float(frames), state, method=SAVi.step,
                                              mutable=["intermediates"])
  attention = variables["intermediates"]["processor"]["corrector"]["attention"][-1]     # [B, K, N]
  b, k, n = attention.shape
  grid = math.isqrt(n)
  centres = (2.0 * jnp.arange(grid, dtype=jnp.float32) + 1.0) / grid - 1.0
  rows, cols = jnp.repeat(centres, grid), jnp.tile(centres, grid)                        # [N], row-major cells
  metres = depth.astype(jnp.float32) / 1000.0
  h, w = metres.shape[-2:]
  cells = metres.reshape(b, grid, h // grid, grid, w // grid).mean(axis=(2, 4)).reshape(b, n)
  mass = attention.sum(axis=-1)                                                          # [B, K]
  weights = attention / jnp.maximum(mass, 1e-6)[..., None]
  where = jnp.stack([weights @ rows, weights @ cols, jnp.einsum("bkn,bn->bk", weights, cells)], axis=-1)
  where = jnp.where((mass >= MIN_ATTENTION)[..., None], where, 0.0)
  return jnp.concatenate([slots, where.astype(slots.dtype)], axis=-1), predicted
