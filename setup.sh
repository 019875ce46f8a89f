#!/usr/bin/env bash
# One-command setup (README).
#   bash setup.sh                 .venv (requirements.txt: bpy 4.5 LTS, numpy, OpenImageIO,
#                                 pytest, ...) and the demo: an adaptive render of a sample
#                                 scene -> out/cornell.lp.exr + out/cornell.lp.png
#   bash setup.sh --no-demo       install only
#   bash setup.sh --all-versions  also .venv-4.2 and .venv-5.0 (Blender 4.2 LTS and 5.0, for
#                                 the cross-version integration tests that CI runs)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$ROOT"
PYTHON="${PYTHON:-python3.11}"
command -v "$PYTHON" >/dev/null || { echo "error: $PYTHON not found (bpy needs Python 3.11)" >&2; exit 2; }
demo=1; versions=0
for a in "$@"; do
  case "$a" in
    --no-demo) demo=0 ;;
    --all-versions) versions=1 ;;
    *) echo "error: unknown option $a" >&2; exit 2 ;;
  esac
done

make_venv() {  # make_venv DIR REQUIREMENTS...
  local dir="$1" stamp="$1/.requirements.sha" want req args=()
  shift
  want="$(cat "$@" | sha256sum | cut -d' ' -f1)"
  for req in "$@"; do args+=(-r "$req"); done
  if [ ! -x "$dir/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "[setup] creating $dir from $* (bpy is large: a few minutes)"
    rm -rf "$dir"
    "$PYTHON" -m venv "$dir"
    "$dir/bin/python" -m pip install -q --upgrade pip
    "$dir/bin/python" -m pip install -q "${args[@]}"
    echo "$want" > "$stamp"
  fi
  "$dir/bin/python" -c "import bpy, numpy, OpenImageIO; print('[setup] $dir: bpy', bpy.app.version_string, '| numpy', numpy.__version__, '| OpenImageIO', OpenImageIO.VERSION_STRING)"
}

# the main environment also carries the farm stack (Dask, OpenJD, Node for the Flamenco test)
make_venv .venv requirements.txt requirements-farm.txt
if [ "$versions" = 1 ]; then
  make_venv .venv-4.2 requirements-4.2.txt
  make_venv .venv-5.0 requirements-5.0.txt
fi
if [ "$demo" = 1 ]; then
  mkdir -p out
  echo "[setup] demo: adaptive render of sample_blends/cornell.blend with LP at 16 spp"
  ./cycles-adaptive render sample_blends/cornell.blend --method lp --spp 16 --out out/cornell.lp.exr --overwrite
  echo "[setup] wrote out/cornell.lp.exr and out/cornell.lp.png"
fi
