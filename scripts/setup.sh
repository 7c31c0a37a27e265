#!/usr/bin/env bash
# One-shot set-up for a fresh Debian/Ubuntu machine with Python >= 3.11:
#   * installs Debian's libusb-1.0-0 (open3d, imported by pytorch_volumetric, needs it) when missing,
#   * installs Debian's chromium (the viewer's browser test) when missing,
#   * creates .venv/ at the repository root,
#   * installs torch as a CPU build unless an NVIDIA GPU is present (a bare `torch` pulls GBs of CUDA),
#   * installs activetouch (editable) with its test extras.
# Idempotent: re-running only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TORCH_VERSION=${TORCH_VERSION:-2.13.0}

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    echo "[setup] installing libusb-1.0-0 (needed by open3d)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

# Debian's chromium: tests/test_viewer.py opens the 3-D viewer (`activetouch view`) in headless Chromium
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
    if command -v apt-get >/dev/null 2>&1; then
        echo "[setup] installing chromium (the viewer test renders the scene in headless Chromium)"
        SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null \
            || echo "[setup] note: could not install chromium; tests/test_viewer.py skips its browser check"
    else
        echo "[setup] note: no apt-get here: install Chromium yourself for the viewer's browser test" \
             "(tests/test_viewer.py skips it without one)"
    fi
fi

"$PY" -c 'import sys; assert sys.version_info >= (3, 11), "activetouch needs Python >= 3.11"'
[ -x .venv/bin/python ] || "$PY" -m venv .venv
VPY=.venv/bin/python
$VPY -m pip install -q --upgrade pip >/dev/null 2>&1 || true

# torch: no package index address is written here. Indexes come from the user's pip configuration
# (pip.conf / PIP_INDEX_URL / PIP_FIND_LINKS) or, for PyTorch's CPU wheels, from ACTIVETOUCH_TORCH_INDEX
# (see README "Installing"). Order: CUDA build when an NVIDIA GPU is present; else a CPU build (+cpu) that
# the pip configuration can find (a local wheel folder, a mirror); else the CPU build from
# ACTIVETOUCH_TORCH_INDEX; else the default build, with a note (on Linux that is the multi-GB CUDA build).
if ! $VPY -c "import torch" 2>/dev/null; then
    TMPW=$(mktemp -d)
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
        echo "[setup] NVIDIA GPU found: installing torch==$TORCH_VERSION (CUDA build)"
        $VPY -m pip install -q "torch==$TORCH_VERSION"
    elif $VPY -m pip download -q --no-deps -d "$TMPW" "torch==$TORCH_VERSION+cpu" >/dev/null 2>&1 \
            && ls "$TMPW"/torch-*+cpu-*.whl >/dev/null 2>&1; then
        echo "[setup] installing the CPU build of torch==$TORCH_VERSION found through the pip configuration"
        $VPY -m pip install -q "$TMPW"/torch-*.whl
    elif [ -n "${ACTIVETOUCH_TORCH_INDEX:-}" ]; then
        echo "[setup] installing the CPU build of torch==$TORCH_VERSION from \$ACTIVETOUCH_TORCH_INDEX"
        $VPY -m pip install -q "torch==$TORCH_VERSION+cpu" --extra-index-url "$ACTIVETOUCH_TORCH_INDEX"
    else
        echo "[setup] no CPU build of torch==$TORCH_VERSION is reachable through your pip configuration and"
        echo "[setup] ACTIVETOUCH_TORCH_INDEX is unset: installing the default build (on Linux the CUDA build,"
        echo "[setup] several GB). Set ACTIVETOUCH_TORCH_INDEX to PyTorch's CPU wheel index for the CPU build."
        $VPY -m pip install -q "torch==$TORCH_VERSION"
    fi
    rm -rf "$TMPW"
fi

echo "[setup] installing activetouch and its dependencies"
# (pip's "Location ... is ignored" lines come from machines with local mirrors: noise, filtered out)
$VPY -m pip install -q -e ".[test]" 2> >(grep -v "is ignored: it is neither" >&2)
echo "[setup] done: $($VPY -c 'import activetouch, torch; print("activetouch", activetouch.__version__, "| torch", torch.__version__)')"
