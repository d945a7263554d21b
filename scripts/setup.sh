#!/usr/bin/env bash
# Idempotent set-up for roboshape: a .venv with the pinned requirements, roboshape itself installed into it editable
# (so `import roboshape` works from any folder, a notebook's too), then a Vulkan device that SAPIEN accepts
# (Mesa >= 24.3 from bookworm-backports on a GPU-less Debian 12; skipped where SAPIEN already finds one).
# Cheap the second time: the venv is keyed by a hash of requirements.txt, the editable install by whether the venv
# already imports this checkout's roboshape from outside it, the Vulkan probe by a stamp file.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3.11}
VENV=.venv
PIP_VERSION=26.3
say() { printf 'setup: %s\n' "$*" >&2; }
die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }

command -v "$PYTHON" >/dev/null || die "$PYTHON not found; install Python 3.11 (or run with PYTHON=/path/to/python3.11)."
req_hash=$(sha256sum requirements.txt | cut -c1-16)
stamp="$VENV/.requirements-$req_hash"
if [ ! -f "$stamp" ]; then
  say "creating $VENV and installing requirements.txt (about 2 minutes on a fresh machine)"
  [ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV" || die "could not create $VENV; install python3.11-venv."
  # The pip that Python 3.11's venv bundles spends most of the install choosing among the index's files (it checks
  # every wheel's tags one by one); a current pip, installed first, resolves the same set of packages several times
  # faster.
  "$VENV/bin/pip" install --quiet --disable-pip-version-check "pip==$PIP_VERSION" || die "could not install pip $PIP_VERSION into $VENV."
  # --no-compile: Python compiles a module's bytecode when it is first imported (the Makefile keeps it even under
  # PYTHONDONTWRITEBYTECODE), so set-up does not compile the many modules of TensorFlow, torch and JAX that
  # roboshape never imports
  "$VENV/bin/pip" install --quiet --disable-pip-version-check --no-compile -r requirements.txt 2> >(grep -v "is ignored: it is neither" >&2) \
    || die "pip install -r requirements.txt failed (see above)."
  rm -f "$VENV"/.requirements-* "$VENV/.vulkan-ok"
  touch "$stamp"
fi

# Whether the venv, run outside the repository without PYTHONPATH, imports roboshape from this checkout.
here=$(pwd -P)
installed() {
  (cd / && env -u PYTHONPATH "$here/$VENV/bin/python" -c 'import os, sys, roboshape
sys.exit(os.path.dirname(os.path.dirname(os.path.realpath(roboshape.__file__))) != sys.argv[1])' "$here") 2>/dev/null
}
if ! installed; then
  say "installing roboshape into $VENV (editable: this checkout, as pyproject.toml describes it)"
  "$VENV/bin/pip" install --quiet --disable-pip-version-check --no-deps -e . || die "pip install -e . failed (see above)."
  installed || die "$VENV imports another roboshape than $here even after pip install -e .: see '$VENV/bin/pip show roboshape'."
fi

probe() { "$VENV/bin/python" -m roboshape.sim.probe >/dev/null 2>&1; }
if [ ! -f "$VENV/.vulkan-ok" ]; then
  if ! probe; then
    say "SAPIEN finds no Vulkan rendering device; installing Mesa's CPU Vulkan driver from bookworm-backports"
    [ -r /etc/os-release ] && . /etc/os-release
    [ "${VERSION_CODENAME:-}" = bookworm ] || die "no Vulkan device and this is not Debian 12: install a Vulkan driver with VK_KHR_external_semaphore_fd (Mesa >= 24.3 lavapipe, or a GPU driver), then rerun."
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then
      if command -v sudo >/dev/null && sudo -n true 2>/dev/null; then SUDO=sudo; else
        die "installing Mesa from bookworm-backports needs root: run 'sudo make setup' once, then rerun."; fi
    fi
    src=/etc/apt/sources.list.d/debian.sources
    if [ ! -f /etc/apt/sources.list.d/backports.sources ]; then
      [ -f "$src" ] || die "$src not found: add bookworm-backports to your apt sources by hand, then rerun."
      awk 'BEGIN{RS="";ORS="\n\n"} NR==1' "$src" \
        | sed -e 's/^Suites: .*/Suites: bookworm-backports/' -e '/^#/d' | $SUDO tee /etc/apt/sources.list.d/backports.sources >/dev/null
    fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers libvulkan1 >/dev/null \
      || die "apt-get install of mesa-vulkan-drivers from bookworm-backports failed (see above)."
    probe || die "SAPIEN still finds no rendering device after installing Mesa; run '$VENV/bin/python -m roboshape.sim.probe' to see why."
  fi
  touch "$VENV/.vulkan-ok"
fi
