#!/usr/bin/env bash
# The whole test suite in two lanes at once, one per core of the 2-core machines it runs on:
#   service: tests/service (mostly waiting on job processes and servers on 127.0.0.1), two
#            CPU-heavy core files (MOVED below) and then the Blender add-in's tests (real bpy,
#            its own venv)
#   core:    every other test
# The run lasts as long as its longest lane, so the split keeps them about even. With the
# Blender tests after the core lane (CI of b77d0f2): service 907 s, core 1348 + 169 s, 1786 s
# in all; split as here (6de4fb5): service 1114 + 193 s, core 1266 s, 1391 s in all; at 9a2cecc
# (clean clone, nothing else running): service 934 + 142 s, core 1001 s, 18 min 58 s with set-up.
# Each lane has its own pytest base temp; both logs are printed when both are done, and the
# suite fails when either lane fails or collects nothing (pytest exits 5 then).
# Usage (what `make test` runs): tests/run_lanes.sh VENV_BIN BLENDER_VENV_BIN
set -uo pipefail
cd "$(dirname "$0")/.."
BIN=${1:?the service venv bin folder}
BLENDER_BIN=${2:?the Blender venv bin folder}
# about 200 s of the core lane (the two-branch LEAP clip, the worker-count determinism runs)
MOVED=(tests/test_two_branches.py tests/test_determinism.py)
work=$(mktemp -d "${TMPDIR:-/tmp}/handretarget-tests.XXXXXX")
trap 'rm -rf "$work"' EXIT

ignore=(--ignore=tests/service)
for f in "${MOVED[@]}"; do ignore+=("--ignore=$f"); done

(
  "$BIN/python" -m pytest --durations=40 --basetemp="$work/service" tests/service "${MOVED[@]}" \
    > "$work/service.log" 2>&1
  echo $? > "$work/service.rc"
  HANDRETARGET_REQUIRE_BLENDER=1 "$BLENDER_BIN/python" -m pytest --basetemp="$work/blender" \
    dcc_client/tests_blender > "$work/blender.log" 2>&1
  echo $? > "$work/blender.rc"
) &
(
  "$BIN/python" -m pytest --durations=40 --basetemp="$work/core" tests "${ignore[@]}" > "$work/core.log" 2>&1
  echo $? > "$work/core.rc"
) &
wait

status=0
for lane in service core blender; do
  echo "=================================== lane: $lane ==================================="
  cat "$work/$lane.log" 2>/dev/null || echo "(no log: the lane did not run)"
  rc=$(cat "$work/$lane.rc" 2>/dev/null || echo 1)
  echo "lane $lane exited with $rc"
  [ "$rc" = 0 ] || status=1
done
exit $status
