#!/usr/bin/env bash
# One-step set-up: headless OpenGL system libraries (Debian/Ubuntu) and a virtual environment
# in .venv with the suite and its test/benchmark extras. Safe to re-run.
set -euo pipefail
cd "$(dirname "$0")"

need=()
# EGL + Mesa: headless OpenGL (llvmpipe without a GPU); xvfb + GLX: the viewer's window test
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglx-mesa0 xvfb; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
    if ! command -v apt-get >/dev/null; then
        echo "setup.sh: install EGL + Mesa (${need[*]}) with your system's package manager" >&2
        exit 1
    fi
    sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${need[@]}"
fi

python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test]"
echo "set up: activate with 'source .venv/bin/activate'"
