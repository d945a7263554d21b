"""Checks that SAPIEN finds a Vulkan rendering device: renders one tiny camera image.

`python -m roboshape.sim.probe` exits 0 and prints the device when rendering works, else exits 1 with the reason.
Used by scripts/setup.sh to decide whether Mesa's CPU Vulkan driver must be installed.
"""
import sys


def render_probe() -> str:
  """Renders a 16x16 image in a fresh SAPIEN scene; returns the render device's name. Raises if none."""
  import sapien  # pylint: disable=import-outside-toplevel
  scene = sapien.Scene()
  camera = scene.add_camera("probe", 16, 16, 1.0, 0.01, 10.0)
  scene.update_render()
  camera.take_picture()
  rgba = camera.get_picture("Color")
  if rgba.shape[:2] != (16, 16):
    raise RuntimeError(f"unexpected probe image shape {rgba.shape}")
  return str(sapien.render.get_device_summary()).strip().splitlines()[0] if hasattr(
      sapien.render, "get_device_summary") else "ok"


def main() -> int:
  try:
    device = render_probe()
  except Exception as e:  # pylint: disable=broad-except
    print(f"roboshape: SAPIEN cannot render: {e}. Run `make setup` (installs Mesa >= 24.3 on Debian 12).",
          file=sys.stderr)
    return 1
  print(f"SAPIEN renders on: {device}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
