#!/usr/bin/env bash
# Sets up a virtual environment in .venv with everything the project needs.
# Idempotent: make calls it whenever pyproject.toml is newer than the install stamp.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ -z "${PYTHON:-}" ]; then
    for p in python3.11 python3.12 python3; do command -v "$p" >/dev/null 2>&1 && { PYTHON=$p; break; }; done
fi
if ! "${PYTHON:-python3}" -c 'import sys; sys.exit(0 if sys.version_info[:2] in ((3, 11), (3, 12)) else 1)'; then
    echo "error: Python 3.11 or 3.12 is required (found $("${PYTHON:-python3}" --version 2>&1));" \
         "set PYTHON=/path/to/python3.11" >&2
    exit 1
fi

# Open3D links against libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "setup: installing libusb-1.0-0 (needed by Open3D)"
        apt-get update -qq >/dev/null
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "error: Open3D needs the system library libusb-1.0 (Debian/Ubuntu: sudo apt-get install libusb-1.0-0)" >&2
        exit 1
    fi
fi

if [ ! -x .venv/bin/python ]; then
    echo "setup: creating .venv"
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# torch first, pinned: the CPU wheel on this machine's disk (a loose pin pulls a CUDA build). A CUDA build of
# torch >= 2.11 that is already in .venv stays (a GPU machine's, README 'On a GPU machine').
if ! .venv/bin/python -c 'import torch, sys
v = tuple(int(x) for x in torch.__version__.split("+")[0].split(".")[:2])
sys.exit(0 if torch.__version__.startswith("2.13.0") or (torch.version.cuda and v >= (2, 11)) else 1)' 2>/dev/null; then
    echo "setup: installing torch==2.13.0"
    .venv/bin/python -m pip install -q torch==2.13.0
fi
echo "setup: installing the project and its dependencies"
.venv/bin/python -m pip install -q -e '.[dev]'
.venv/bin/python -c 'import open3d, torch, rosbags, pycolmap' || { echo "error: dependency import failed" >&2; exit 1; }
# The fused CPU kernels of the encoding (nerf/csrc) compile here, once (about a minute on 2 cores), and not
# inside the first window fit of `make all`. Without a usable compiler this warns and the fits use the
# pure-torch reference; any later change to nerf/csrc rebuilds them on first use.
echo "setup: building the fused encoding kernels"
.venv/bin/python -c 'from nerf._ext import load_permuto_ext; print("setup: kernels", "ready" if load_permuto_ext("cpu") else "unavailable: the pure-torch reference is used")'
echo "setup: done"
