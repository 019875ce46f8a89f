#!/usr/bin/env bash
# One-command setup (README): creates .venv with the pinned packages
# (requirements.txt: bpy 4.5 LTS, numpy, OpenImageIO, pytest, ...), then,
# unless --no-demo, runs the main job on a sample scene: an adaptive render that
# writes out/cornell.lp.exr and its PNG preview.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$ROOT"
PYTHON="${PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null || { echo "error: $PYTHON not found (bpy needs Python 3.11)" >&2; exit 2; }
stamp=".venv/.requirements.sha"
want="$(sha256sum requirements.txt | cut -d' ' -f1)"
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] creating .venv with the pinned packages (bpy is large: a few minutes)"
  "$PYTHON" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -r requirements.txt
  echo "$want" > "$stamp"
fi
.venv/bin/python -c "import bpy, numpy, OpenImageIO; print('[setup] bpy', bpy.app.version_string, '| numpy', numpy.__version__, '| OpenImageIO', OpenImageIO.VERSION_STRING)"
if [ "${1:-}" != "--no-demo" ]; then
  mkdir -p out
  echo "[setup] demo: adaptive render of sample_blends/cornell.blend with LP at 16 spp"
  ./cycles-adaptive render sample_blends/cornell.blend --method lp --spp 16 --out out/cornell.lp.exr --overwrite
  echo "[setup] wrote out/cornell.lp.exr and out/cornell.lp.png"
fi
