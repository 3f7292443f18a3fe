#!/usr/bin/env bash
# Installs everything the project needs into .venv (idempotent: a second run with an unchanged
# pyproject.toml only checks). System packages: libLLVM-19 for Mitsuba's vectorized CPU backend.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
LLVM19=/usr/lib/x86_64-linux-gnu/libLLVM-19.so

as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null 2>&1; then sudo -n "$@"; else return 1; fi
}

if [ ! -e "$LLVM19" ] && [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
  echo "[install] libLLVM-19 missing: installing Debian package libllvm19 (Mitsuba's llvm_ad_rgb needs it)"
  if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19; }; then
    echo "[install] warning: could not install libllvm19; rendering falls back to the slow scalar_rgb variant" >&2
  fi
fi

stamp=.venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)
if [ -f "$stamp" ]; then
  echo "[install] .venv is up to date"
  exit 0
fi
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch==2.13.0 is pinned in pyproject.toml: that exact version installs a CPU build from local disk.
.venv/bin/python -m pip install -q -e '.[dev]'
rm -f .venv/.installed-*
touch "$stamp"
echo "[install] .venv ready"
