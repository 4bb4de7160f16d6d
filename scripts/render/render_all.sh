#!/usr/bin/env bash
# Renders the physically rendered CW-ToF validation set into bags/rendered/
# (not part of CI; ~1 h on 2 cores). See scripts/render/README.md.
#   scripts/render/render_all.sh [NAME ...]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
VENV="${TTOF_RENDER_VENV:-/work/render-venv}"
export DRJIT_LIBLLVM_PATH="${DRJIT_LIBLLVM_PATH:-/opt/llvm19/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1}"
export TTOF_RENDER_CACHE="${TTOF_RENDER_CACHE:-/work/render-cache}"
nice -n 5 "$VENV/bin/python" scripts/render/render_set.py "$@"
