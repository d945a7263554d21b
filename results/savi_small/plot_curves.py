"""Draws the validation FG-ARI and reconstruction MSE of the SAVi runs in this folder into fg_ari_curves.png.

  .venv/bin/python results/savi_small/plot_curves.py

Each <name>.json here is a copy of a run's <workdir>/savi/val_metrics.json (see README.md for the commands).
"""
import json
import os

import matplotlib

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # pylint: disable=wrong-import-position

HERE = os.path.dirname(os.path.abspath(__file__))
RUNS = {  # file -> legend
    "small_64x64_shared.json": "64x64, shared init (the former :small)",
    "small_pooled_per_slot.json": "32x32 pooled, per-slot init (the :small of the third session)",
    "pooled_lr1e-3.json": "32x32 pooled, per-slot init, lr 1e-3",
    "pooled_per_slot_3iters_clip2.json": "32x32, per-slot, 3 iterations, 24 clips x 2",
    "pooled_shared_3iters_clip1.json": "32x32, shared, 3 iterations, 48 single frames",
    "pooled_predictor_identity_init.json": "32x32, per-slot, predictor starting as LayerNorm",
    "probe_single_frames_b16.json": "probe.py: 16 single frames per step (6 val episodes x 12 frames)",
    "probe_3iters_last_gradient.json": "probe, 16 frames: 3 iterations, last-iteration gradient",
    "probe_queries.json": "probe, 16 frames: learned queries (no noise)",
    "probe_queries_3iters_last_gradient.json": "probe, 16 frames: queries + 3 iterations + last gradient",
    "probe_queries_3iters_last_clips2_idinit.json": "probe, 8 clips x 2: as above + LayerNorm predictor",
    "small_v5.json": "queries, 3 it., last gradient, 8 clips x 2, launch.py (fifth session)",
    "probe_slot_colour.json": "probe, 8 clips x 2: as above + one colour per slot",
    "probe_slot_colour_9slots.json": "probe, 8 clips x 2: as above + one colour per slot, 9 slots",
    "small_v6_clips2.json": "one colour per slot, 9 slots, 8 clips x 2, launch.py",
    "small_v7.json": "v7, the :small of the sixth session (one colour per slot, 9 slots, 4 clips x 6), launch.py",
    "small_v8_6slots_shaded.json": "6 slots, shaded colour per slot, 4 clips x 6, launch.py",
    "small_v9_9slots_shaded.json": "9 slots, shaded colour per slot, 4 clips x 6, launch.py",
    "small_v10_pixel_mlp_decoder.json": "v10, v7 + a per-pixel MLP decoder (learned vector per pixel), launch.py",
    "small_v12_learned_shaded.json": "v12, v11 + a shaded colour per slot, launch.py",
    "small_v13_7slots.json": "v13, v11 with 7 slots, launch.py",
    "small_v11x_12000.json": "v11 resumed at step 8000 on a 12 000-step schedule, launch.py",
    "small_v14_palette.json": "v14, v11 with two colours per slot (hard pick per pixel), launch.py",
    "small_v15_dark_shade.json": "v15, v11 with its colour or a dark shade of it per pixel, launch.py",
    "small_v17_depth_shaded.json": "v17, v11 + depth (weight 1) + a shaded colour per slot, launch.py",
    "small_v18_depth_only.json": "v18, v11 trained on depth alone (rgb_weight 0), 6000-step schedule, launch.py",
    "small_v11_learned_position.json": "v11, the :small now: v7 + a learned vector per 8x8 decoder grid cell, launch.py",
    "small_v16_depth.json": "v16, v11 + depth as a second target (weight 1), launch.py",
    "small_v19_depth_quarter.json": "v19, v11 + depth as a second target (weight 0.25), launch.py",
}


def main():
  fig, axes = plt.subplots(1, 2, figsize=(12, 7.6), dpi=130)
  colours = plt.get_cmap("tab20")
  for i, (name, label) in enumerate(RUNS.items()):
    with open(os.path.join(HERE, name)) as f:
      history = json.load(f)
    steps = [h["step"] for h in history]
    style = dict(marker="o", markersize=2.5, color=colours(i % 20), linestyle="-" if i < 10 else "--", label=label,
                 linewidth=2.2 if i >= len(RUNS) - 3 else 1.2)
    axes[0].plot(steps, [h["fg_ari"] for h in history], **style)
    if "recon_mse" in history[0]:  # the probe records the training loss only
      axes[1].plot(steps, [h["recon_mse"] for h in history], **style)
  axes[0].axhline(0.6, color="grey", linestyle="--", linewidth=1)
  axes[0].text(50, 0.56, "bar: FG-ARI 0.6", color="grey", fontsize=8)
  axes[0].set_ylim(-0.15, 0.7)
  axes[0].set_ylabel("validation FG-ARI")
  axes[1].set_ylabel("validation reconstruction MSE")
  axes[1].set_ylim(0.0, 0.08)
  for ax in axes:
    ax.set_xlabel("training step")
    ax.grid(alpha=0.3)
  fig.legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="lower center", ncol=2, frameon=False)
  fig.subplots_adjust(bottom=0.43, top=0.93, wspace=0.22)
  fig.suptitle("SAVi on the :small push set (8 validation episodes x 24 frames), 2-core CPU")
  out = os.path.join(HERE, "fg_ari_curves.png")
  fig.savefig(out)
  print(out)


if __name__ == "__main__":
  main()
