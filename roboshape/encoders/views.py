"""Several cameras: a frozen encoder run on each view of `env.cameras`, its tokens joined into one set per frame.

`with_views(encoder, cameras)` wraps an encoder that reads the front camera's frames ("image", and "segmentation"
or "depth" when it reads them): for every camera it runs the same step with the same params on that camera's frames
(roboshape/envs/camera.py `keys`: "wrist_image" in place of "image", ...), each view with its own recurrent state,
and returns the views' tokens one after the other, [B, V * N, D + V]. Every token gets V more entries, the one-hot of
its view, so the trunk's shared token projection adds a learned embedding per view (the trunk gives a frame's
tokens no order, so this is how it tells the views apart); an all-zero token (the `objects` encoder's absent
object) stays all zero, so the trunk still masks it out.

One encoder serves every view: the registration says whether it may (Kind.views): the `objects` control and
fixed-weight encoders read any view alike, and SAVi and the AE are pretrained on clips of every view of env.cameras.

Where a token's object is (FrozenEncoder.points, for policy.hand_relative) comes from the front view's calibration:
the front view's tokens keep their points, another view's tokens have none (the wrist view itself moves with the
hand, so its tokens are relative to the hand already).
"""
import dataclasses
import functools

from roboshape.envs import camera


def _view_keys(view: str, inputs):
  """The keys of `view`'s observation that stand for `inputs`, the front camera's names ("state" stays itself)."""
  names = dict(zip(camera.keys(camera.FRONT), camera.keys(view)))
  return [names.get(k, k) for k in inputs]


def _renamed(view: str, inputs, obs):
  """The observation `obs` as `view` sees it, the keys `inputs` alone."""
  seen = camera.view(obs, view)
  return {k: seen[k] for k in inputs}


def _step(base_step, base_inputs, cameras, params, carry, obs):
  """Each view's tokens [B, N, D] with its one-hot appended, joined: [B, V * N, D + V]; carry: one per view."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  from roboshape.models import encoder as encoder_lib  # pylint: disable=import-outside-toplevel
  out, carries = [], []
  for v, view in enumerate(cameras):
    tokens, c = base_step(params, carry[v], encoder_lib.select(base_inputs, _renamed(view, base_inputs, obs)))
    present = jnp.any(tokens != 0, axis=-1, keepdims=True).astype(tokens.dtype)                  # [B, N, 1]
    onehot = jnp.zeros(tokens.shape[:-1] + (len(cameras),), tokens.dtype).at[..., v].set(1.0)
    out.append(jnp.concatenate([tokens, onehot * present], axis=-1))
    carries.append(c)
  return jnp.concatenate(out, axis=1), tuple(carries)


def _points(base_points, cameras, num_tokens, token_dim, tokens):
  """Where each token's object is: the front view's tokens by the base encoder's points, the others none."""
  import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
  front = cameras.index(camera.FRONT)
  where, valid = base_points(tokens[..., front * num_tokens:(front + 1) * num_tokens, :token_dim])
  pad = [(0, 0)] * (where.ndim - 2)
  before, after = front * num_tokens, (len(cameras) - front - 1) * num_tokens
  return (jnp.pad(where, pad + [(before, after), (0, 0)]), jnp.pad(valid, pad + [(before, after)]))


def reads_frames(encoder) -> bool:
  """Whether `encoder` reads any of the front camera's frames (an encoder of the state alone does not)."""
  return any(k in camera.keys(camera.FRONT) for k in encoder.inputs)


def with_views(encoder, cameras):
  """The FrozenEncoder `encoder` run on each of `cameras` (the front one among them), as the module docstring says;
  `encoder` itself when there is one camera or it reads no frames."""
  cameras = camera.check(cameras)
  if len(cameras) == 1 or not reads_frames(encoder):
    return encoder
  base_inputs = tuple(encoder.inputs)
  inputs = tuple(dict.fromkeys(k for view in cameras for k in _view_keys(view, base_inputs)))
  points = None
  if encoder.points is not None:
    points = functools.partial(_points, encoder.points, cameras, encoder.num_tokens, encoder.token_dim)
  return dataclasses.replace(
      encoder, step=functools.partial(_step, encoder.step, base_inputs, cameras),
      init_state=lambda batch_size: tuple(encoder.init_state(batch_size) for _ in cameras),
      num_tokens=encoder.num_tokens * len(cameras), token_dim=encoder.token_dim + len(cameras), inputs=inputs,
      points=points, identity=f"{encoder.identity}+views:{'+'.join(cameras)}")

