#!/usr/bin/env bash
# Installs everything the project needs into .venv (idempotent: a second run with an unchanged
# pyproject.toml only checks). System packages: libLLVM-19 for Mitsuba's vectorized CPU backend.
# Usage: scripts/install.sh [--blender[=4.5]] [--browser] [--proxy]
#   --blender  also Blender as a Python module (the 'blender' extra of pyproject.toml, for scripts/render_blender.py),
#              installed without its dependencies: bpy's metadata pins numpy<2, and the project's numpy 2 renders fine.
#   --blender=4.5  Blender 4.5 LTS instead (the 'blender-4-5' extra), the same way; --blender=5 is --blender.
#   --browser  also Chromium (Debian package chromium), for the test that renders /docs and /redoc headless.
#   --proxy    also HAProxy (Debian package haproxy), for the test that runs two API replicas behind
#              deploy/haproxy/denoiser.cfg (the reverse proxy of docker-compose.yml).
# PIP (default: .venv/bin/python -m pip) is the pip the Blender step asks and installs with.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
LLVM19=/usr/lib/x86_64-linux-gnu/libLLVM-19.so
blender=""  # the extra of pyproject.toml to install bpy from
browser=0
proxy=0
for arg in "$@"; do
  case "$arg" in
    --blender|--blender=5) blender=blender ;;
    --blender=4.5) blender=blender-4-5 ;;
    --blender=*) echo "[install] unknown Blender version '${arg#--blender=}' (--blender: 5.0, --blender=4.5: 4.5 LTS)" >&2
                 exit 2 ;;
    --browser) browser=1 ;;
    --proxy) proxy=1 ;;
    -h|--help) sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "[install] unknown option '$arg' (options: --blender, --browser, --proxy)" >&2; exit 2 ;;
  esac
done

as_root() {
  if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null 2>&1; then sudo -n "$@"; else return 1; fi
}

install_project() {
  if [ ! -e "$LLVM19" ] && [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    echo "[install] libLLVM-19 missing: installing Debian package libllvm19 (Mitsuba's llvm_ad_rgb needs it)"
    if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19; }; then
      echo "[install] warning: could not install libllvm19; rendering falls back to the slow scalar_rgb variant" >&2
    fi
  fi
  local stamp
  stamp=.venv/.installed-$(sha256sum pyproject.toml | cut -c1-16)
  if [ -f "$stamp" ]; then
    echo "[install] .venv is up to date"
    return
  fi
  [ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  # torch==2.13.0 is pinned in pyproject.toml: that exact version installs a CPU build from local disk.
  .venv/bin/python -m pip install -q -e '.[dev]'
  rm -f .venv/.installed-*
  touch "$stamp"
  echo "[install] .venv ready"
}

install_blender() {
  # The one pin is the extra's in pyproject.toml ($1: blender or blender-4-5).
  local requirement version pip shown
  requirement=$(.venv/bin/python -c 'import sys, tomllib
print(tomllib.load(open("pyproject.toml", "rb"))["project"]["optional-dependencies"][sys.argv[1]][0])' "$1")
  version=${requirement#*==}
  pip=${PIP:-.venv/bin/python -m pip}
  # pip's answer is read whole first: grep -q stops reading at its match, and pipefail would count pip's SIGPIPE
  shown=$($pip show bpy 2>/dev/null || true)
  if grep -qx "Version: $version" <<< "$shown"; then
    echo "[install] $requirement is installed"
    return
  fi
  echo "[install] installing $requirement (Blender as a Python module, without its numpy<2 pin)"
  $pip install -q --no-deps "$requirement"
}

# A Debian package for one test ($1: its command, $2: the package, $3: what needs it); already there: only checked.
install_debian_package() {
  if command -v "$1" >/dev/null 2>&1 || [ -x "/usr/sbin/$1" ]; then
    echo "[install] $1 is installed"
    return
  fi
  echo "[install] installing Debian package $2 ($3)"
  if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$2"; }; then
    echo "[install] could not install $2 (needs root or sudo, and Debian's package lists)" >&2
    return 1
  fi
}

install_project
if [ -n "$blender" ]; then install_blender "$blender"; fi
if [ "$browser" = 1 ]; then
  install_debian_package chromium chromium "the headless browser test of /docs and /redoc"
fi
if [ "$proxy" = 1 ]; then
  install_debian_package haproxy haproxy "the test of API replicas behind deploy/haproxy/denoiser.cfg"
fi
