#!/usr/bin/env bash
# The project's two commands (see README):
#   ./dev.sh demo          the main job on the simulated stage
#   ./dev.sh test [ARGS]   the whole test suite (pytest ARGS)
# and, for convenience, ./dev.sh <piezo-stage args>.
# Each creates or reuses the virtual environment .venv at the repository root and
# (re)installs the package when its install files changed.
set -euo pipefail
cd "$(dirname "$0")"

py=${PYTHON:-}
if [ -z "$py" ]; then
  for c in python3.11 python3; do command -v "$c" >/dev/null 2>&1 && { py=$c; break; }; done
fi
[ -n "$py" ] || { echo "dev.sh: error: python3.11 not found" >&2; exit 2; }

if [ ! -x .venv/bin/python ]; then
  "$py" -m venv .venv
fi
stamp=.venv/.piezo_stage_install_stamp
want=$(cat setup.py setup.cfg package.xml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[ros,test]"
  # the nv200 backend's package (and its tests): it declares Python >= 3.12 but runs on
  # 3.11 (every module imports and its tests pass here), so it is installed past that
  # check, after the test extra, never as a dependency pip would refuse
  .venv/bin/python -m pip install --quiet --disable-pip-version-check \
    --ignore-requires-python "nv200==1.6.0"
  echo "$want" > "$stamp"
fi

cmd=${1:-demo}
[ $# -gt 0 ] && shift
case "$cmd" in
  test)
    # with no test selection: the tests that start no node process on two workers, then
    # those that do (marked slow or realtime) one at a time: a node set's timing does not
    # survive a second worker's CPU load on a 2-core machine
    if [ $# -eq 0 ] || [ "$*" = "-q" ]; then
      # (each phase ends with its 15 slowest tests: where the suite's time goes)
      .venv/bin/python -m pytest "$@" -m "not slow and not realtime" --durations=15
      exec .venv/bin/python -m pytest "$@" -m "slow or realtime" -n 0 --durations=15
    fi
    exec .venv/bin/python -m pytest "$@" ;;
  demo) exec .venv/bin/piezo-stage demo "$@" ;;
  *)    exec .venv/bin/piezo-stage "$cmd" "$@" ;;
esac
