"""SAVi: slot attention for video, the object-centric encoder that roboshape pretrains by reconstruction.

Per frame t, a CNN turns the image into a set of N features; slot attention (the corrector) refines the K slots
predicted from frame t-1 against those features; a transformer block (the predictor) maps the corrected slots to
the initial slots of frame t+1; a spatial-broadcast decoder reconstructs the frame from the corrected slots, with
per-slot RGB and alpha masks normalised over the slots. The first frame starts from slots drawn from a learned
Gaussian.

  model = build_model(config.savi)
  out = model.apply({"params": params}, video, rngs={"slots": key})   # video float [B, T, H, W, 3] in [0, 1]
  out["slots"] [B, T, K, D], out["recon"] [B, T, H, W, 3], out["masks"] [B, T, K, H, W], out["rgb"] [B, T, K, H, W, 3]

  slots, state = model.apply({"params": params}, frame, state, first=t == 0, method=SAVi.step)   # one frame of it

Defaults follow SAVi-S on 64x64 images: 32-channel 5x5 convolutions, slot size 128, an 8x8 broadcast grid.
"""
import math
from typing import Dict, Optional, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from roboshape.models import layers

INIT_MEANS = ("shared", "per_slot", "queries")   # SlotInitializer(mean=...)
SLOT_GRADIENTS = ("full", "last")                # SlotAttention(gradient=...)
DECODER_RGBS = ("spatial", "slot", "slot_shaded", "slot_palette", "slot_dark")  # SpatialBroadcastDecoder(rgb=...)
DECODER_POSITIONS = ("coords", "learned")          # SpatialBroadcastDecoder(position=...)


class CNNEncoder(nn.Module):
  """Convolutions with ReLU, a position embedding, then a per-location MLP.

  images [B, H, W, 3] -> features [B, N, F] with N = (H / prod(strides)) * (W / prod(strides)).
  """
  features: Sequence[int] = (32, 32, 32, 32, 32)
  kernel_size: int = 5
  strides: Sequence[int] = (1, 1, 1, 1, 1)
  mlp_size: int = 64
  output_size: int = 64

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
  """K first-frame slots: drawn from learned diagonal Gaussians, or K learned vectors.

  mean="shared": one mean [D] for all slots, so only the noise tells the slots apart (the Slot Attention paper's
  initialisation). mean="per_slot": a learned mean per slot [K, D], so the first frame's slots start from K
  distinct learned points rather than from noise around one point. The log-scale [D] is shared.
  mean="queries": K learned vectors and no noise at all (learned queries): every episode starts from the same
  slots, so a slot can come to stand for a part of the scene that is always there (the robot, the table).
  """
  num_slots: int
  slot_size: int
  mean: str = "shared"

  @nn.compact
  def __call__(self, noise: jnp.ndarray) -> jnp.ndarray:
    """noise [..., K, D] standard normal -> slots [..., K, D] = mean + exp(log_scale) * noise (= mean, "queries")."""
    if self.mean not in INIT_MEANS:
      raise ValueError(f"unknown slot initialisation mean {self.mean!r}; use one of {INIT_MEANS}.")
    shape = (self.slot_size,) if self.mean == "shared" else (self.num_slots, self.slot_size)
    mean = self.param("mean", nn.initializers.normal(1.0), shape)
    if self.mean == "queries":
      return jnp.broadcast_to(mean, noise.shape)
    log_scale = self.param("log_scale", nn.initializers.zeros, (self.slot_size,))
    return mean + jnp.exp(log_scale) * noise


class SlotAttention(nn.Module):
  """Iterative slot attention: attention normalised over the slots (they compete for each input), a weighted mean
  of the values per slot, a GRU update and a residual MLP.

  gradient="full": back-propagation runs through every iteration. gradient="last": the first-order implicit
  gradient (the iterations approximate a fixed point): all but the last iteration run under stop_gradient, and the
  initial slots get the last iteration's gradient straight through (slots' = sg(slots) + init - sg(init)), so the
  learned initial slots (and SAVi's predictor) still train; the backward pass is one iteration long.
  slots [B, K, D], inputs [B, N, F] -> slots [B, K, D]; equivariant to permutations of the K slots.
  """
  num_iterations: int = 2
  mlp_size: int = 256
  epsilon: float = 1e-8
  gradient: str = "full"

  @nn.compact
  def __call__(self, slots: jnp.ndarray, inputs: jnp.ndarray, num_iterations: Optional[int] = None) -> jnp.ndarray:
    """num_iterations (static): this call's number of iterations, the module's own when None; the parameters are
    the same whatever the number."""
    if self.gradient not in SLOT_GRADIENTS:
      raise ValueError(f"unknown slot-attention gradient {self.gradient!r}; use one of {SLOT_GRADIENTS}.")
    slot_size, init = slots.shape[-1], slots
    inputs = nn.LayerNorm(name="norm_inputs")(inputs)
    keys = nn.Dense(slot_size, use_bias=False, name="key")(inputs)        # [B, N, D]
    values = nn.Dense(slot_size, use_bias=False, name="value")(inputs)    # [B, N, D]
    query_dense = nn.Dense(slot_size, use_bias=False, name="query")
    norm_slots = nn.LayerNorm(name="norm_slots")
    gru = nn.GRUCell(slot_size, name="gru")
    mlp = layers.MLP(self.mlp_size, slot_size, layernorm=True, residual=True, name="mlp")
    iterations = self.num_iterations if num_iterations is None else num_iterations
    for i in range(iterations):
      if self.gradient == "last" and i == iterations - 1 and i > 0:
        slots = jax.lax.stop_gradient(slots) + init - jax.lax.stop_gradient(init)
      queries = query_dense(norm_slots(slots)) / math.sqrt(slot_size)     # [B, K, D]
      logits = jnp.einsum("bkd,bnd->bkn", queries, keys)                  # [B, K, N]
      attention = jax.nn.softmax(logits, axis=1)                          # over the slots
      self.sow("intermediates", "attention", attention)                   # kept only when asked for (mutable)
      weights = attention / (attention.sum(axis=-1, keepdims=True) + self.epsilon)
      updates = jnp.einsum("bkn,bnd->bkd", weights, values)               # weighted mean, [B, K, D]
      slots, _ = gru(slots, updates)
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
  predictor_identity_init: bool = False
  gradient: str = "full"

  def setup(self):
    self.corrector = SlotAttention(self.num_iterations, self.slot_mlp_size, gradient=self.gradient)
    self.predictor = layers.TransformerBlock(self.predictor_heads, self.predictor_mlp_size, self.predictor_identity_init)

  def __call__(self, predicted: jnp.ndarray, features: jnp.ndarray,
               num_iterations: Optional[int] = None) -> Tuple[jnp.ndarray, jnp.ndarray]:
    corrected = self.corrector(predicted, features, num_iterations)
    return corrected, self.predictor(corrected)


class Upsample(nn.Module):
  """A learned upsampling by `stride` (a plain convolution when stride is 1, a Dense layer when the kernel is 1x1).

  "subpixel": a convolution to stride * stride * C channels, then depth-to-space; "transpose": a transposed
  convolution. Both learn the same family of upsamplings; XLA's CPU backend runs the sub-pixel form faster
  (measured: a 3x3 stride-2 layer, forward + backward, 4x less time), GPUs run both well.
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
      raise ValueError(f"unknown upsampling {self.mode!r}; use 'subpixel' or 'transpose'.")
    y = nn.Conv(self.features * s * s, kernel, padding="SAME", name="conv")(x)
    b, h, w, _ = y.shape
    y = y.reshape(b, h, w, s, s, self.features).transpose(0, 1, 3, 2, 4, 5)
    return y.reshape(b, h * s, w * s, self.features)


class SpatialBroadcastDecoder(nn.Module):
  """Decodes every slot on its own into RGB and an alpha logit; masks are the softmax of the alphas over slots.

  A learned position embedding is added to each slot broadcast over a grid_size x grid_size grid, then each layer
  upsamples by its stride (see Upsample), with ReLU; a final 1x1 layer gives RGB and alpha (rgb="spatial"), or
  alpha only, with each slot painted in one colour, a linear map of the slot (rgb="slot": a slot can then explain
  only a region of one colour, which pushes the masks to follow colours), or that colour times a per-pixel
  brightness gain in (0, 2) from the CNN (rgb="slot_shaded": one hue with its shading, e.g. a white robot with dark
  joints; the gain starts at 1 everywhere, so the mode starts as "slot"), or one of the slot's `palette_size` colours
  per pixel, picked by the CNN (rgb="slot_palette": a hard choice, the softmax's gradient passed straight through,
  so a slot paints e.g. white links and dark joints but never the greys between; the choice starts at colour 0,
  i.e. as "slot"), or the same hard pick between the slot's colour and that colour times the slot's own dark factor
  in (0, 0.5) (rgb="slot_dark": two shades of one hue, e.g. white links and grey joints, but no other hue).

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
  grid_size: int = 8
  features: Sequence[int] = (64, 64, 64, 64)
  kernel_size: int = 5
  strides: Sequence[int] = (2, 2, 2, 1)
  upsampling: str = "subpixel"
  rgb: str = "spatial"
  position: str = "coords"
  palette_size: int = 2
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
    elif self.rgb in ("slot", "slot_shaded"):
      alpha = nn.Dense(1, name="output")(x)[..., 0].reshape(batch, num_slots, *x.shape[1:3])
      colour = nn.Dense(3, name="colour")(slots)                           # [B, K, 3]
      rgb = jnp.broadcast_to(colour[:, :, None, None, :], (*alpha.shape, 3))
      if self.rgb == "slot_shaded":
        shade = nn.Dense(1, kernel_init=nn.initializers.zeros, name="shade")(x)
        rgb = rgb * 2.0 * jax.nn.sigmoid(shade.reshape(*alpha.shape, 1))   # [B, K, H, W, 3]
    elif self.rgb in ("slot_palette", "slot_dark"):
      alpha = nn.Dense(1, name="output")(x)[..., 0].reshape(batch, num_slots, *x.shape[1:3])
      if self.rgb == "slot_palette":
        size = self.palette_size
        palette = nn.Dense(3 * size, name="colour")(slots).reshape(batch, num_slots, size, 3)
      else:
        size = 2
        colour = nn.Dense(3, name="colour")(slots)                         # [B, K, 3]
        dark = 0.5 * jax.nn.sigmoid(nn.Dense(1, name="dark")(slots))       # [B, K, 1]
        palette = jnp.stack([colour, colour * dark], axis=2)               # [B, K, 2, 3]
      logits = nn.Dense(size, kernel_init=nn.initializers.zeros, name="choice")(x)
      soft = jax.nn.softmax(logits.reshape(*alpha.shape, size), axis=-1)    # [B, K, H, W, P]
      hard = jax.nn.one_hot(jnp.argmax(soft, axis=-1), size, dtype=soft.dtype)
      choice = soft + jax.lax.stop_gradient(hard - soft)                    # forward: one-hot; backward: softmax
      rgb = jnp.einsum("bkhwp,bkpc->bkhwc", choice, palette)               # [B, K, H, W, 3]
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
  Slot attention runs first_frame_iterations times on the first frame (num_iterations when 0), from the initial
  slots, and num_iterations times on every later frame, from the predictor's slots.
  With input_pool = f > 1 the frames are average-pooled by f before the encoder and the decoder reconstructs the
  pooled frames (a cheaper model of the same frames; the masks are 1/f of the frames' resolution).
  """
  num_slots: int = 11
  slot_size: int = 128
  init_mean: str = "shared"
  num_iterations: int = 2
  first_frame_iterations: int = 0
  slot_gradient: str = "full"
  slot_mlp_size: int = 256
  encoder_features: Sequence[int] = (32, 32, 32, 32, 32)
  encoder_kernel_size: int = 5
  encoder_strides: Sequence[int] = (1, 1, 1, 1, 1)
  encoder_mlp_size: int = 64
  feature_size: int = 64
  predictor_heads: int = 4
  predictor_mlp_size: int = 256
  predictor_identity_init: bool = False
  decoder_grid_size: int = 8
  decoder_features: Sequence[int] = (64, 64, 64, 64)
  decoder_kernel_size: int = 5
  decoder_strides: Sequence[int] = (2, 2, 2, 1)
  decoder_upsampling: str = "subpixel"
  decoder_rgb: str = "spatial"
  decoder_position: str = "coords"
  decoder_depth: bool = False
  input_pool: int = 1

  def setup(self):
    self.encoder = CNNEncoder(self.encoder_features, self.encoder_kernel_size, self.encoder_strides,
                              self.encoder_mlp_size, self.feature_size)
    self.initializer = SlotInitializer(self.num_slots, self.slot_size, self.init_mean)
    self.processor = Processor(self.num_iterations, self.slot_mlp_size, self.predictor_heads,
                               self.predictor_mlp_size, self.predictor_identity_init, self.slot_gradient)
    self.decoder = SpatialBroadcastDecoder(self.decoder_grid_size, self.decoder_features, self.decoder_kernel_size,
                                           self.decoder_strides, self.decoder_upsampling, self.decoder_rgb,
                                           self.decoder_position, depth=self.decoder_depth)

  @property
  def output_resolution(self) -> int:
    return self.decoder_grid_size * math.prod(self.decoder_strides)

  def initial_slots(self, noise: jnp.ndarray) -> jnp.ndarray:
    """noise [..., K, D] standard normal -> the first frame's slots [..., K, D] from the learned Gaussian."""
    return self.initializer(noise)

  def decode(self, slots: jnp.ndarray) -> Dict[str, jnp.ndarray]:
    """slots [B, K, D] -> dict(recon [B, H, W, 3], rgb [B, K, H, W, 3], masks [B, K, H, W])."""
    return self.decoder(slots)

  @property
  def iterations_first(self) -> int:
    """Slot-attention iterations on the first frame of a video."""
    return self.first_frame_iterations or self.num_iterations

  def encode_frame(self, frame: jnp.ndarray) -> jnp.ndarray:
    """frame [B, H, W, 3] in [0, 1] -> the encoder's features [B, N, F]."""
    return self.encoder(pool_frames(frame, self.input_pool))

  def correct(self, features: jnp.ndarray, state: jnp.ndarray,
              first: bool = False) -> Tuple[jnp.ndarray, jnp.ndarray]:
    """(features [B, N, F], predicted slots [B, K, D]) -> (slots [B, K, D], next state); `first` as in `step`."""
    return self.processor(state, features, self.iterations_first if first else None)

  def step(self, frame: jnp.ndarray, state: jnp.ndarray, first: bool = False) -> Tuple[jnp.ndarray, jnp.ndarray]:
    """One frame: (frame [B, H, W, 3] in [0, 1], predicted slots [B, K, D]) -> (slots [B, K, D], next state).

    first (static): the frame is a video's first, `state` its initial slots (first_frame_iterations apply)."""
    return self.correct(self.encode_frame(frame), state, first)

  def __call__(self, video: jnp.ndarray, init_slots: Optional[jnp.ndarray] = None,
               decode: bool = True) -> Dict[str, jnp.ndarray]:
    """video [B, T, H, W, 3] in [0, 1] (and optionally the first frame's slots [B, K, D]) -> dict:

    slots [B, T, K, D] (corrected), predicted [B, T, K, D] (each frame's prediction for the next one), and when
    `decode`: recon [B, T, h, w, 3], rgb [B, T, K, h, w, 3], masks [B, T, K, h, w] with h = H / input_pool
    (and depth [B, T, h, w], slot_depth [B, T, K, h, w] with decoder_depth).
    """
    batch = video.shape[0]
    if init_slots is None:
      noise = jax.random.normal(self.make_rng("slots"), (batch, self.num_slots, self.slot_size))
      init_slots = self.initial_slots(noise)
    video = pool_frames(video, self.input_pool)
    features = _unfold_time(self.encoder(_fold_time(video)), batch)      # [B, T, N, F]

    def body(processor, carry, frame_features):
      corrected, predicted = processor(carry, frame_features)
      return predicted, (corrected, predicted)

    scan = nn.scan(body, variable_broadcast="params", variable_axes={"intermediates": 1}, split_rngs={"params": False},
                   in_axes=1, out_axes=1)
    if self.iterations_first == self.num_iterations:
      _, (slots, predicted) = scan(self.processor, init_slots, features)
    else:                                       # the first frame on its own, with its own number of iterations
      corrected, carry = self.processor(init_slots, features[:, 0], self.iterations_first)
      slots, predicted = corrected[:, None], carry[:, None]
      if features.shape[1] > 1:
        _, (rest, rest_predicted) = scan(self.processor, carry, features[:, 1:])
        slots = jnp.concatenate([slots, rest], axis=1)
        predicted = jnp.concatenate([predicted, rest_predicted], axis=1)
    out = {"slots": slots, "predicted": predicted}
    if decode:
      decoded = self.decoder(_fold_time(slots))
      out.update({k: _unfold_time(v, batch) for k, v in decoded.items()})
    return out


def input_pool(savi_config) -> int:
  """The factor config.savi.pool by which SAVi average-pools the frames (1 when the config has no such field)."""
  return int(savi_config.get("pool", 1))


def loss_weights(savi_config) -> Tuple[float, float]:
  """(rgb, depth): the weights config.savi.train.rgb_weight (1 when absent) and depth_weight (0 when absent); the
  model predicts depth when the depth weight is > 0."""
  train = savi_config.train
  return float(train.get("rgb_weight", 1.0)), float(train.get("depth_weight", 0.0))


def decoder_grid_size(savi_config, resolution: int) -> int:
  """The broadcast grid's side: config.savi.decoder.grid_size, or (resolution / pool) / prod(strides) when it is 0."""
  grid = int(savi_config.decoder.grid_size)
  return grid if grid > 0 else resolution // input_pool(savi_config) // math.prod(savi_config.decoder.strides)


def build_model(savi_config, resolution: int) -> SAVi:
  """The SAVi module a `config.savi` section describes (see configs/common.py:savi_config) for square frames of
  `resolution` pixels a side."""
  c = savi_config
  return SAVi(
      num_slots=int(c.num_slots), slot_size=int(c.slot_size), init_mean=str(c.get("init_mean", "shared")),
      num_iterations=int(c.num_iterations), first_frame_iterations=int(c.get("first_frame_iterations", 0)),
      slot_gradient=str(c.get("slot_gradient", "full")),
      slot_mlp_size=int(c.slot_mlp_size),
      encoder_features=tuple(c.encoder.features), encoder_kernel_size=int(c.encoder.kernel_size),
      encoder_strides=tuple(c.encoder.strides), encoder_mlp_size=int(c.encoder.mlp_size),
      feature_size=int(c.encoder.output_size),
      predictor_heads=int(c.predictor.num_heads), predictor_mlp_size=int(c.predictor.mlp_size),
      predictor_identity_init=bool(c.predictor.get("identity_init", False)),
      decoder_grid_size=decoder_grid_size(c, resolution), decoder_features=tuple(c.decoder.features),
      decoder_kernel_size=int(c.decoder.kernel_size), decoder_strides=tuple(c.decoder.strides),
      decoder_upsampling=str(c.decoder.upsampling), decoder_rgb=str(c.decoder.get("rgb", "spatial")),
      decoder_position=str(c.decoder.get("position", "coords")),
      decoder_depth=loss_weights(c)[1] > 0,
      input_pool=input_pool(c))
