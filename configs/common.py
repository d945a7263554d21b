"""The pieces every roboshape experiment config is built from.

An experiment file (e.g. `configs/pick_savi.py`) calls `get_config(task, encoder, variant)`; its variant comes from
the command line as `--config=configs/pick_savi.py:tiny`. Variants:

  paper: the paper's scale (2000 demos per task, 100 rollouts x 3 seeds per cell); meant for GPU machines.
  small: a scale that trains and evaluates on a 2-core CPU in hours per cell (2000 demos per task, as the paper).
  tiny:  a handful of episodes and steps, for tests and `make demo`.

Every field can be overridden on the command line, e.g. `--config.policy.train.steps=100`.
Each section below belongs to one part of the code base (named in its function's docstring).
"""
import ml_collections

from roboshape import encoders
from roboshape import envs
from roboshape import fields
from roboshape import rundir
from roboshape.encoders import columns
from roboshape.envs import camera
from roboshape.errors import UserError

TASKS = envs.TASKS
VARIANTS = ("paper", "small", "tiny")
LEVELS = envs.LEVEL_NAMES  # the training distribution and the three shifts (roboshape/envs/palettes.py)
STAGES = rundir.STAGES     # every stage, in the order a run takes them
# How a task's policies are run at control time where it differs from policy_config's eval defaults, for every
# encoder alike. Place: a mode drawn from the GMM rather than the mixture mean, which averages "close" with "open"
# and "lift" with "descend" at the grasp, so the gripper hovers half shut; and one frame of history, since with ten
# the policy reads its next action off its own past motion and copies its own slowing. Push and pick keep the
# defaults. The trials that chose this (each setting alone and both):
# `git show cb0d979:results/small/place_state/README.md`.
TASK_CONTROL = {"place": dict(action="sample", history=1)}
# Behaviour-cloning steps where a task's :small policy needs more than policy_config's: place's validation action
# MSE still falls at 5000 steps, and three times the steps lift its state control several-fold
# (results/small/recipe/README.md, place_state_15k). Push and pick keep the default.
TASK_SMALL_STEPS = {"place": 15_000}
# Behaviour-cloning settings where a task differs from policy_config's, in every variant. Place: the steps where
# the demo's gripper command changes (grasp and release, two of a demo's ~46) weigh ten times the others, since a
# mixture fitted to every step alike leaves the release to a light mode (results/small/recipe/README.md,
# place_state_recipe). Push and pick keep the default.
TASK_TRAIN = {"place": dict(change_weight=10.0)}


def _pick(variant: str, *, paper, small, tiny):
  """The value of `variant` among one value per variant, each given by its name."""
  return {"paper": paper, "small": small, "tiny": tiny}[variant]


def env_config(variant: str) -> ml_collections.ConfigDict:
  """The RoboShape world (roboshape/envs): what each reset randomises and what the camera sees."""
  return ml_collections.ConfigDict(dict(
      resolution=64,            # square RGB camera in front of the robot, pixels per side (16..512)
      min_distractors=1,
      max_distractors=4,
      max_episode_steps=0,      # 0: the task's own horizon (>= 1.5x the expert's 95th percentile)
      sim_backend="physx_cpu",  # or "physx_cuda" (physics on a GPU); each worker owns one env either way
      # also store the camera's depth (uint16 mm) in the dataset, for pretrain.train.depth_weight (:small's)
      depth=_pick(variant, paper=False, small=True, tiny=False),
      # the cameras rendered and stored (roboshape/envs/camera.py `CAMERAS`): the front one alone by default
      cameras=camera.DEFAULT,
  ))


def sim_config(variant: str) -> ml_collections.ConfigDict:
  """The numpy bridge to the simulator (roboshape/sim)."""
  del variant
  return ml_collections.ConfigDict(dict(
      num_workers=0,            # 0: one worker per CPU core
      step_timeout=120.0,       # seconds a worker may take for one reset / step before it is killed
      episode_timeout=600.0,    # seconds a worker may take for one expert episode (collection)
  ))


def data_config(variant: str) -> ml_collections.ConfigDict:
  """The RoboShape dataset (roboshape/data): expert demos in RLDS/TFDS, at <dir>/roboshape_<task>/1.0.0.

  Only successful expert episodes are kept: train takes the first `train_episodes` successes among seeds 0, 1, ...,
  val the first max(min_val_episodes, round(val_fraction * train_episodes)) among seeds 1000000, 1000001, ...
  """
  return ml_collections.ConfigDict(dict(
      dir="",                   # "": <workdir>/data; set it to share one dataset per task between experiments
      train_episodes=_pick(variant, paper=2000, small=2000, tiny=4),  # :small's: results/small/recipe
      val_fraction=0.05,        # validation episodes, from seeds disjoint from the training ones
      min_val_episodes=1,
  ))


def pretrain_config(variant: str) -> ml_collections.ConfigDict:
  """The pretrain stage (roboshape/train/pretrain.py): how whichever model the run's encoder pretrains is trained.

  One section for every pretrained model rather than one per model: the AE is the control that holds pretraining
  equal to SAVi's, and a shared section makes that true by construction (an override reaches the training of
  whichever model the run trains). What describes a model lives in its own section (savi, ae).

  train.clip_norm bounds the global norm of the loss's gradient. The loss is minimised as a mean over a clip's pixel
  values (clip_length x h x w x 3, h x w the frames the model reconstructs); train.clip_norm_of says which loss the
  bound is stated for: "mean", that loss itself, or "sum", the loss summed over those values as SAVi's is, the
  division by their number done where the clip and the model are known (pretrain.make_optimizer), so a longer clip
  or larger frames keep the bound's meaning. As Adam's epsilon scales with the clip, :paper's "sum" gives SAVi's
  updates exactly; :small and :tiny bound the mean.
  """
  return ml_collections.ConfigDict(dict(
      train=ml_collections.ConfigDict(dict(
          steps=_pick(variant, paper=100_000, small=8_000, tiny=20),
          batch_size=_pick(variant, paper=64, small=4, tiny=2),
          clip_length=6,
          learning_rate=_pick(variant, paper=2e-4, small=4e-4, tiny=1e-3),
          warmup_steps=_pick(variant, paper=2500, small=200, tiny=2),
          clip_norm=0.05,           # global gradient norm, of the loss clip_norm_of names
          clip_norm_of=_pick(variant, paper="sum", small="mean", tiny="mean"),   # "mean" or "sum" (SAVi's)
          # > 0: also reconstruct depth (metres), weighted so against the RGB MSE; needs env.depth=True data
          depth_weight=_pick(variant, paper=0.0, small=0.25, tiny=0.0),
          # p > 0: a pixel's RGB error weighs its segment's share of the frame ** -p (small objects count more; it
          # reads the segmentation in pretraining only). :small weighs every segment of a frame alike (p = 1), as the
          # recipe study adopted (results/small/recipe/README.md)
          mask_weight=_pick(variant, paper=0.0, small=1.0, tiny=0.0),
          checkpoint_every=_pick(variant, paper=1000, small=250, tiny=10),
          keep_checkpoints=3,
          log_every=_pick(variant, paper=50, small=10, tiny=1),
      )),
      eval=ml_collections.ConfigDict(dict(
          every=_pick(variant, paper=5000, small=500, tiny=20),   # steps between validations (and after the last)
          episodes=_pick(variant, paper=32, small=8, tiny=1),     # validation episodes
          frames=_pick(variant, paper=24, small=24, tiny=6),      # first frames of each episode
      )),
      # (): one run with config.seed, in <workdir>/<encoder>/. (s1, s2, ...): one run per seed in
      # <encoder>/seed_<s>/, the one with the best final validation served (<encoder>/selected.json; the metric is
      # the encoder's, e.g. SAVi's FG-ARI). Needs pretrain.eval.episodes >= 1 with two seeds or more.
      train_seeds=(),
      # "": the run's pretrain stage trains its encoder in its workdir. A path: the workdir of another run of the
      # same task and encoder whose pretrain stage trained it, served from there (its config.json must agree on
      # everything pretraining reads); the run then has no pretrain stage. A grid sets it for a column with
      # policy options, to the plain column's run (roboshape/grid.py).
      from_workdir="",
  ))


def _frame_encoder(variant: str) -> ml_collections.ConfigDict:
  """The CNN that turns a frame into features, SAVi's and the AE's alike (roboshape/models/savi.py:CNNEncoder)."""
  return ml_collections.ConfigDict(dict(
      features=_pick(variant, paper=(32,) * 5, small=(32,) * 5, tiny=(16,) * 5),
      kernel_size=5,
      strides=_pick(variant, paper=(1, 1, 1, 1, 1), small=(2, 1, 1, 1, 1), tiny=(2, 1, 1, 1, 1)),
      mlp_size=_pick(variant, paper=64, small=64, tiny=32),
      # SAVi-S: the MLP maps back to the CNN's 32 channels
      output_size=_pick(variant, paper=32, small=64, tiny=32),
  ))


def _frame_decoder(variant: str) -> ml_collections.ConfigDict:
  """The spatial-broadcast decoder that draws a frame, SAVi's and the AE's alike (SpatialBroadcastDecoder)."""
  return ml_collections.ConfigDict(dict(
      grid_size=0,            # broadcast grid side; 0: env.resolution / pool / prod(strides), 8x8 at 64x64
      features=_pick(variant, paper=(64, 64, 64, 64), small=(32, 16), tiny=(16, 16, 16)),
      kernel_size=_pick(variant, paper=5, small=3, tiny=3),
      strides=_pick(variant, paper=(2, 2, 2, 1), small=(2, 2), tiny=(2, 2, 2)),
      # stride-2 layers: "subpixel" (conv + depth-to-space; fast on CPU) or "transpose" (SAVi-S's)
      upsampling=_pick(variant, paper="transpose", small="subpixel", tiny="subpixel"),
      # grid position embedding: "coords" (a linear map of the pixel coordinates) or "learned" (a free vector
      # per grid cell; with kernel_size=1 and strides all 1 the decoder is a per-pixel MLP)
      position=_pick(variant, paper="coords", small="learned", tiny="coords"),
  ))


_FRAME_POOL = dict(paper=1, small=2, tiny=1)   # frames are average-pooled by this factor before the model sees them


def savi_config(variant: str) -> ml_collections.ConfigDict:
  """SAVi, the object-centric video encoder (roboshape/models/savi.py; trained by the pretrain stage).

  paper: SAVi-S (google-research/slot-attention-video, savi_conditional_small.py, with its unconditional learned
  Gaussian first slots) on 64x64 frames, with its corrector (one slot-attention iteration per frame and no MLP: SAVi
  refines the slots across frames through the recurrence) and two departures: a fifth encoder conv, as the paper
  says, and 4 coordinate channels in the position embeddings.
  small: the same design made cheap enough for a 2-core CPU (frames pooled to 32x32, masks scored at 64x64; a
  stride-2 first conv; a decoder of alpha masks only, from a learned vector per grid cell, with one colour per slot;
  9 slots, no spares), with learned queries without noise, 3 iterations with the last one's gradient, a predictor
  that starts as LayerNorm and a depth target (pretrain.train.depth_weight); the variants tried:
  results/savi_small/README.md.
  tiny: a toy model for tests and `make demo`.
  """
  decoder = _frame_decoder(variant)
  # "spatial": RGB per pixel from the CNN; "slot": one colour per slot (a Dense of the slot), masks spatial
  decoder.rgb = _pick(variant, paper="spatial", small="slot", tiny="spatial")
  return ml_collections.ConfigDict(dict(
      # robot, cube, target/bin, up to 4 distractors, table, backdrop (+ 2 spares in paper and tiny)
      num_slots=_pick(variant, paper=11, small=9, tiny=11),
      slot_size=_pick(variant, paper=128, small=128, tiny=32),
      pool=_pick(variant, **_FRAME_POOL),
      # > 0: slot attention on the frame's full pixel grid, each pixel the CNN's cell plus a convolution of this
      # many channels of the unpooled frame (roboshape/models/savi.py:FullGrid); 0: on the CNN's grid
      full_grid=0,
      # first frame's slots: "shared" (one learned mean + noise) or "queries" (K learned vectors, no noise)
      init_mean=_pick(variant, paper="shared", small="queries", tiny="shared"),
      num_iterations=_pick(variant, paper=1, small=3, tiny=2),  # slot-attention iterations per frame (SAVi-S: 1)
      # "full": backprop through every iteration; "last": only through the last (first-order implicit gradient)
      slot_gradient=_pick(variant, paper="full", small="last", tiny="full"),
      slot_mlp_size=_pick(variant, paper=0, small=256, tiny=64),  # the corrector's residual MLP; 0: none (SAVi-S)
      encoder=_frame_encoder(variant),
      predictor=ml_collections.ConfigDict(dict(
          num_heads=4,
          mlp_size=_pick(variant, paper=256, small=256, tiny=64),
          # True: the predictor starts as LayerNorm (no mixing of slots) at step 0
          identity_init=_pick(variant, paper=False, small=True, tiny=False),
      )),
      decoder=decoder,
      eval=ml_collections.ConfigDict(dict(         # SAVi's validation (roboshape/eval/slots.py)
          background_ids=(0, 1),                   # segmentation ids FG-ARI and mIoU ignore: backdrop and table
          figure_frames=4,                         # frames in each validation's decomposition figure
      )),
  ))


def ae_config(variant: str) -> ml_collections.ConfigDict:
  """The `ae` encoder, a frame autoencoder (roboshape/models/ae.py; trained by the pretrain stage).

  Its frame encoder, decoder and pooling default to SAVi's (the same tables), so that the AE differs from SAVi only
  in having no objects; its training is the pretrain section, SAVi's.
  """
  return ml_collections.ConfigDict(dict(
      latent_size=0,            # D, the width of the one token per frame; 0: savi.slot_size
      pool=_pick(variant, **_FRAME_POOL),
      encoder=_frame_encoder(variant),
      decoder=_frame_decoder(variant),
  ))


def state_config(variant: str) -> ml_collections.ConfigDict:
  """The `state` encoder, the privileged state as one token (roboshape/encoders/state.py)."""
  del variant
  return ml_collections.ConfigDict(dict(
      # state fields the token leaves out (e.g. ("cube_quat",)): an ablation of what a field is worth
      withhold=(),
      relative=True,            # False: absolute positions only (no cube or goal relative to the hand)
  ))


def baseline_config(variant: str) -> ml_collections.ConfigDict:
  """Frozen global encoders loaded from official checkpoints (roboshape/baselines)."""
  del variant
  return ml_collections.ConfigDict(dict(
      r3m=ml_collections.ConfigDict(dict(
          arch="resnet50",          # resnet18 | resnet34 | resnet50
          path="",                  # "": ~/.r3m/r3m_{18,34,50}/model.pt, where the R3M package caches it
          input_size=224,           # side frames are resized to before the network (0: the frames' own size)
      )),
      dino=ml_collections.ConfigDict(dict(
          arch="vits16",            # vits16 | vitb16
          path="",                  # "": ~/.cache/torch/hub/checkpoints/dino_{deitsmall,vitbase}16_pretrain.pth
          input_size=224,           # 0: the frames' own size, with resized position embeddings
          patch_tokens=False,       # True: the patch tokens follow the CLS token
      )),
  ))


def policy_config(variant: str) -> ml_collections.ConfigDict:
  """The transformer policy with a GMM head, trained by behaviour cloning (roboshape/models, roboshape/train/bc.py)."""
  return ml_collections.ConfigDict(dict(
      history=10,               # H: frames the trunk sees in training (and the number of time embeddings)
      width=_pick(variant, paper=256, small=128, tiny=32),
      num_layers=_pick(variant, paper=8, small=4, tiny=1),
      num_heads=_pick(variant, paper=4, small=4, tiny=2),
      mlp_ratio=4,
      dropout=0.1,
      action_dim=7,
      num_modes=5,              # GMM modes
      min_scale=1e-4,           # floor on the GMM's softplus scales
      # one more token per frame with the robot's own pose (tool centre point, finger opening) from
      # observation/state (roboshape/encoders/proprio.py); off in the paper, which uses no proprioception
      proprio=False,
      # with proprio: each token also carries its object's position relative to the tool centre point, for the
      # encoders whose tokens say where their object is (roboshape/encoders/proprio.py)
      hand_relative=False,
      # pool each frame's tokens into one (a set encoder) before the temporal transformer: T tokens, not T*N;
      # :small's since it lifted pick's object tokens and cut their cost (results/small/recipe/README.md)
      frame_pool=_pick(variant, paper=False, small=True, tiny=False),
      cache_dtype="float32",    # dtype of the cached encoder features ("float16" halves the cache)
      # () one policy trained with config.seed, in <workdir>/policy/; (s1, s2, ...) one policy per training seed, in
      # policy/seed_<s>/, each evaluated on the same evaluation seeds; tables then give mean ± std over them
      train_seeds=(),
      train=ml_collections.ConfigDict(dict(
          steps=_pick(variant, paper=100_000, small=5000, tiny=20),
          batch_size=_pick(variant, paper=256, small=64, tiny=4),
          learning_rate=1e-4,
          weight_decay=1e-4,
          warmup_steps=_pick(variant, paper=2000, small=200, tiny=2),
          grad_clip=1.0,
          # the loss weight of a step where the demo's gripper command changes (grasp, release); 1: none
          change_weight=1.0,
          log_every=_pick(variant, paper=100, small=50, tiny=5),
          eval_every=_pick(variant, paper=2000, small=500, tiny=10),
          checkpoint_every=_pick(variant, paper=5000, small=500, tiny=10),
          val_batch_size=_pick(variant, paper=256, small=128, tiny=16),
          max_val_samples=_pick(variant, paper=20_000, small=5000, tiny=1000),  # action targets per validation pass
      )),
      eval=ml_collections.ConfigDict(dict(
          history=0,              # frames seen at control time; 0: the training history
          action="mean",          # "mean": mixture mean; "sample": a mode drawn by weight, low-noise around it
          noise=0.1,              # for action="sample": the fraction of the mode's scale added as noise
      )),
  ))


def eval_config(variant: str) -> ml_collections.ConfigDict:
  """Closed-loop evaluation (roboshape/eval)."""
  return ml_collections.ConfigDict(dict(
      levels=LEVELS,
      rollouts_per_seed=_pick(variant, paper=100, small=20, tiny=2),
      num_seeds=_pick(variant, paper=3, small=3, tiny=1),
      seed_offset=1_000_000_000,  # env seed = seed_offset + seed_index * 100_000 + rollout (disjoint from demos)
      max_retries=2,            # re-runs of a rollout whose simulator worker died, before it is reported
      videos_per_level=_pick(variant, paper=3, small=3, tiny=1),
      video_fps=20,
  ))


def get_config(task: str, encoder: str, variant: str = "paper") -> ml_collections.ConfigDict:
  """The full config of one experiment: `task` x `encoder` at the scale `variant`. `encoder` may name a column, an
  encoder with options beyond the paper ("savi+proprio": roboshape/encoders/columns.py), whose fields it sets."""
  variant = variant or "paper"
  column = encoder
  if task not in TASKS:
    raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASKS)}.")
  try:
    encoder = columns.parse(column)[0]
  except UserError as e:
    raise ValueError(str(e)) from None
  if variant not in VARIANTS:
    raise ValueError(f"unknown variant {variant!r}; use configs/<exp>.py:<variant> with one of {', '.join(VARIANTS)}.")
  stages = STAGES if encoders.get(encoder).pretrain else tuple(s for s in STAGES if s != "pretrain")
  config = ml_collections.ConfigDict(dict(
      name=f"{task}_{column}",
      task=task,
      encoder=encoder,
      variant=variant,
      seed=0,
      stages=stages,
      env=env_config(variant),
      sim=sim_config(variant),
      data=data_config(variant),
      pretrain=pretrain_config(variant),
      savi=savi_config(variant),
      ae=ae_config(variant),
      state=state_config(variant),
      baselines=baseline_config(variant),
      policy=policy_config(variant),
      eval=eval_config(variant),
  ))
  columns.apply(config, column)
  config.policy.eval.update(TASK_CONTROL.get(task, {}))
  config.policy.train.update(TASK_TRAIN.get(task, {}))
  if variant == "small" and task in TASK_SMALL_STEPS:
    config.policy.train.steps = TASK_SMALL_STEPS[task]
  return config


def override(config: ml_collections.ConfigDict, item: str) -> None:
  """Sets one field from "dotted.field=VALUE" (VALUE a Python literal, e.g. "savi.decoder.strides=(2, 2)"), for
  scripts that take overrides outside launch.py's --config.x flags."""
  fields.put(config, *fields.parse(item))
