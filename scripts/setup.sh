#!/usr/bin/env bash
# Set up layerfit on Debian/Ubuntu: libLLVM >= 16 (Dr.Jit's CPU backend), python3-venv, and a .venv
# with the project installed (editable). Safe to run again; fast when nothing changed.
# `--with-tests` also installs the test tools (pytest, hypothesis, playwright, ruff: the `test` extra);
# `--with-chromium` (or LAYERFIT_CHROMIUM=1) Debian's chromium for the HTML report test, if
# /usr/bin/chromium is missing. scripts/test.sh passes both; the main job (scripts/run.sh) neither.
# `--with-blender` (scripts/test.sh --slow) also makes .venv-blender, Blender as a Python module
# (bpy, scripts/blender-requirements.txt) for the test that renders exports in Blender: it needs
# Python 3.11 and NumPy < 2, so it has a venv of its own; where it cannot be made, that test skips.
# `--with-xvfb` (scripts/test.sh --slow) installs Xvfb and Mesa's software OpenGL for the test that
# renders the MaterialX export with MaterialX's GLSL renderer; without them that test skips.
set -euo pipefail
cd "$(dirname "$0")/.."

with_chromium=${LAYERFIT_CHROMIUM:-0}
with_tests=0
with_blender=0
with_xvfb=0
for arg in "$@"; do
  case "$arg" in
    --with-chromium) with_chromium=1 ;;
    --with-tests) with_tests=1 ;;
    --with-blender) with_blender=1 ;;
    --with-xvfb) with_xvfb=1 ;;
    *) echo "setup: unknown option $arg (known: --with-tests, --with-chromium, --with-blender, --with-xvfb)" >&2; exit 2 ;;
  esac
done

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
  echo "setup: need root (or sudo) to run: $*" >&2; exit 1; fi; }

have_llvm() {  # any libLLVM >= 16 known to the dynamic linker or in the usual folders
  { ldconfig -p 2>/dev/null | grep -o 'libLLVM[^ ]*'; ls /usr/lib/*/libLLVM* /usr/lib/llvm-*/lib/libLLVM* 2>/dev/null; } |
    grep -oE 'libLLVM(-[0-9]+|\.so\.[0-9]+)' | grep -oE '[0-9]+' | awk '$1 >= 16 {found=1} END {exit !found}'
}

apt_updated=0
apt_install() {
  [ "$apt_updated" = 1 ] || { as_root apt-get update -qq; apt_updated=1; }
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

if ! have_llvm; then
  command -v apt-get >/dev/null || { echo "setup: install libLLVM >= 16 (e.g. libllvm19) by hand" >&2; exit 1; }
  echo "setup: installing libLLVM (Dr.Jit's CPU backend needs >= 16)"
  installed=0
  for v in 19 18 17 16; do
    if apt_install "libllvm$v" 2>/dev/null; then installed=1; break; fi
  done
  [ "$installed" = 1 ] || { echo "setup: no libllvm16..19 package found; install libLLVM >= 16" >&2; exit 1; }
fi

if [ "$with_chromium" = 1 ] && [ ! -x /usr/bin/chromium ]; then  # optional, except in CI
  echo "setup: installing chromium (the HTML report test opens the report in it)"
  if ! { command -v apt-get >/dev/null && (apt_install chromium); }; then
    case "${CI:-}" in
      "" | 0 | [Ff]alse) echo "setup: no /usr/bin/chromium; the HTML report test will be skipped" >&2 ;;
      *) echo "setup: CI needs /usr/bin/chromium (the HTML report test); install chromium" >&2; exit 1 ;;
    esac
  fi
fi

if [ "$with_xvfb" = 1 ] && ! command -v xvfb-run >/dev/null; then  # best effort: the test skips
  echo "setup: installing Xvfb and Mesa (MaterialX's GLSL renderer needs an X display)"
  if ! { command -v apt-get >/dev/null && (apt_install xvfb xauth libgl1-mesa-dri); }; then
    echo "setup: no Xvfb; the MaterialX render test will be skipped" >&2
  fi
fi

PY=${PYTHON:-python3}
"$PY" -c 'import sys; assert sys.version_info >= (3, 11), sys.version' 2>/dev/null ||
  { echo "setup: layerfit needs Python >= 3.11 ($PY is older or missing); set PYTHON=..." >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  if ! "$PY" -m venv --help >/dev/null 2>&1 || ! "$PY" -c 'import ensurepip' 2>/dev/null; then
    echo "setup: installing python3-venv"; apt_install python3-venv
  fi
  "$PY" -m venv .venv
fi

# a stamp per install (the project; the project with its test tools): a copy of the
# pyproject.toml it installed, so an edited one installs again
target=. stamp=.venv/.layerfit-installed
if [ "$with_tests" = 1 ]; then target='.[test]' stamp=.venv/.layerfit-installed-test; fi
if [ ! -f "$stamp" ] || ! cmp -s pyproject.toml "$stamp"; then
  echo "setup: installing Python packages into .venv (about a minute the first time)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e "$target"
  cp pyproject.toml "$stamp"
  cp pyproject.toml .venv/.layerfit-installed  # the test tools' install holds the project's
fi

if [ "$with_blender" = 1 ]; then  # best effort: the Blender test skips without it
  blender_py=$(command -v python3.11 || true)
  if [ -z "$blender_py" ]; then
    echo "setup: no python3.11 for Blender's bpy; the Blender export test will be skipped" >&2
  elif [ ! -f .venv-blender/.installed ] || ! cmp -s scripts/blender-requirements.txt .venv-blender/.installed; then
    echo "setup: installing Blender as a Python module into .venv-blender (about 400 MB)"
    if "$blender_py" -m venv .venv-blender && .venv-blender/bin/python -m pip install -q -r scripts/blender-requirements.txt; then
      cp scripts/blender-requirements.txt .venv-blender/.installed
    else
      echo "setup: bpy could not be installed; the Blender export test will be skipped" >&2
      rm -rf .venv-blender
    fi
  fi
fi
