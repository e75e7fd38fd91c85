#!/usr/bin/env bash
# Installs ParaDrive builder into ./.venv: system libraries first, then torch pinned to the
# CPU build that lies on disk here, then the package with the requested extras: `build` (the
# default) brings the builder's packages; without it only the pair reader (paradrive.data).
# Usage: scripts/setup.sh [extras]   e.g. scripts/setup.sh build,test
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1-build}"
PY="${PYTHON:-python3}"

need_apt=()
# open3d links libusb-1.0; pyvista/vtk offscreen needs GL/EGL and X render libraries.
for pkg in libusb-1.0-0 libgl1 libegl1 libxrender1 libosmesa6; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
# The CPU rasterizer kernels are C++, compiled when the package is installed (without a
# compiler the package still installs and the torch-op rasterizer, about 10x slower, runs).
command -v c++ >/dev/null 2>&1 || command -v g++ >/dev/null 2>&1 || need_apt+=(g++)
if [ "${#need_apt[@]}" -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1; then
        SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
    else
        echo "setup: please install ${need_apt[*]} with your system package manager" >&2
    fi
fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
# torch first and pinned, with pip, which finds the CPU build on disk: an unpinned torch, or one
# from another installer, pulls a CUDA build of several GB. The package's own range (torch>=2.4)
# takes the pinned build as it is.
.venv/bin/python -m pip install -q "torch==2.13.0"
target="."
[ -n "$extras" ] && target=".[$extras]"
# The rest with uv (its parallel downloads halve the install: 17 s against 75 s on a two-core
# machine); with pip where uv cannot be installed or cannot install them (uv reads its own
# index settings, UV_INDEX_URL and uv.toml, not pip's). torch stays the one installed above.
# Compiled to bytecode as pip does (uv does not by default): where PYTHONDONTWRITEBYTECODE is
# set, every process would otherwise compile numpy, pyarrow, ray, pydantic ... afresh, 3 CPU
# seconds of a 17 s smoke build and more in every Ray worker.
if ! { .venv/bin/python -m pip install -q uv &&
        .venv/bin/python -m uv pip install -q --compile-bytecode --python .venv/bin/python -e "$target"; }; then
    echo "setup: uv did not install the packages; installing them with pip" >&2
    .venv/bin/python -m pip install -q -e "$target"
fi
# the package itself (an editable install compiles nothing): an edited module is compiled anew
# when imported, the others are read as they are
.venv/bin/python -m compileall -q -j 0 paradrive >/dev/null
echo "setup: ready (.venv, extras: ${extras:-none})"
