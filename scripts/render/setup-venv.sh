#!/usr/bin/env bash
# Sets up the render environment (not the repo's .venv): Mitsuba 3 +
# mitransient + the MCAP writer, and Debian's libLLVM 19 for Dr.Jit (the
# system LLVM aborts with "Cannot select ... fminimum").
set -euo pipefail
VENV="${TTOF_RENDER_VENV:-/work/render-venv}"
python3 -m venv "$VENV"
"$VENV/bin/pip" install --quiet mitsuba==3.9.1 drjit==1.5.0 mitransient==1.3.1 \
    mcap==1.6.0 mcap-ros2-support==0.6.0 zstandard numpy
if [ ! -e /opt/llvm19/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 ]; then
    (cd /tmp && apt-get download libllvm19 && dpkg -x libllvm19_*.deb /opt/llvm19)
fi
echo "ok: export DRJIT_LIBLLVM_PATH=/opt/llvm19/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
