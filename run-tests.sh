#!/usr/bin/env bash
# The project's test command (README; CI runs exactly this after setup):
# the whole suite under Blender 4.5 (.venv), then the bpy integration tests
# under Blender 4.2 and 5.0 (.venv-4.2, .venv-5.0; made by `setup.sh --all-versions`).
# Under CI=true a missing version venv is a failure, elsewhere it is skipped with a note.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
INTEGRATION="tests/test_executor.py tests/test_job.py tests/test_cli.py tests/test_extension.py tests/test_denoise_cli.py tests/test_api.py tests/test_regression_example.py tests/test_oidn_blender.py tests/test_cryptomatte_blender.py"
status=0
run() {  # run VENV ARGS...
  local py="$1/bin/python"; shift
  "$py" -m pytest -q -p no:cacheprovider "$@"
  local rc=$?
  if [ "$rc" -eq 5 ]; then echo "no tests collected under $py: failing" >&2; rc=1; fi
  [ "$rc" -eq 0 ] || status=1
}
[ -x .venv/bin/python ] || { echo "error: .venv missing; run bash setup.sh --no-demo" >&2; exit 2; }
echo "== Blender 4.5 LTS: whole suite"
run .venv tests
for v in 4.2 5.0; do
  if [ -x ".venv-$v/bin/python" ]; then
    echo "== Blender $v: bpy integration tests"
    # shellcheck disable=SC2086
    run ".venv-$v" $INTEGRATION
  elif [ "${CI:-}" = "true" ]; then
    echo "error: .venv-$v missing under CI (setup.sh --all-versions)" >&2; status=1
  else
    echo "note: .venv-$v not installed; Blender $v integration tests skipped (bash setup.sh --all-versions)"
  fi
done
exit "$status"
