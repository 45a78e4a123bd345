#!/usr/bin/env bash
# The project's two commands (see README):
#   ./dev.sh demo          the main job on the simulated stage
#   ./dev.sh test [ARGS]   the whole test suite (pytest ARGS)
# and, for convenience, ./dev.sh <piezo-stage args>; ./dev.sh lock writes requirements.lock
# again (after a change to setup.py's requirements).
# Each creates or reuses the virtual environment .venv at the repository root and
# (re)installs the package when its install files changed.
set -euo pipefail
cd "$(dirname "$0")"

py=${PYTHON:-}
if [ -z "$py" ]; then
  for c in python3.11 python3; do command -v "$c" >/dev/null 2>&1 && { py=$c; break; }; done
fi
[ -n "$py" ] || { echo "dev.sh: error: python3.11 not found" >&2; exit 2; }

cmd=${1:-demo}
# what a command needs installed: the demo and the other commands the package and ROS;
# the tests also their tools (pytest, linters, the vendors' packages)
extras=ros
[ "$cmd" = test ] && extras=ros,test

# uv installs the wheels in seconds where pip takes half a minute: it comes from PATH or,
# through pip, from the package index into .venv/tools; it is given pip's own
# configuration (indexes, find-links, constraints, certificate). Without uv, pip.
# PIEZO_STAGE_INSTALLER=pip: pip alone (as before uv; bench setup's baseline).
uv=$(command -v uv || true)
[ -z "$uv" ] && [ -x .venv/tools/bin/uv ] && uv=.venv/tools/bin/uv
only_pip=$([ "${PIEZO_STAGE_INSTALLER:-}" = pip ] && echo 1 || true)
[ -n "$only_pip" ] && uv=""
pip_config=""
if [ ! -x .venv/bin/python ]; then
  # pip's configuration (its indexes, for uv below) is read beside the new .venv's set-up
  pip_config=$(mktemp)
  "$py" -m pip config list >"$pip_config" 2>/dev/null & pip_config_pid=$!
  if [ -z "$only_pip" ] && [ -z "$uv" ] && "$py" -m venv --without-pip .venv \
       && "$py" -m pip install --quiet --disable-pip-version-check --no-deps --no-compile \
            --target .venv/tools uv >/dev/null 2>&1; then
    uv=.venv/tools/bin/uv
  elif [ -z "$only_pip" ] && [ -n "$uv" ]; then
    "$py" -m venv --without-pip .venv
  else
    rm -rf .venv
    "$py" -m venv .venv
  fi
fi
# pip's configuration as uv's flags (indexes, find-links, constraints, certificate)
uv_flags=()
pip_config_to_uv() {
  if [ -n "$pip_config" ]; then wait "$pip_config_pid" || true; fi
  while IFS= read -r line; do
    key=${line%%=*}; key=${key#*.}; val=${line#*=}; val=${val#\'}; val=${val%\'}
    for v in $val; do
      case "$key" in
        index-url) uv_flags+=(--index-url "$v") ;;
        extra-index-url) uv_flags+=(--extra-index-url "$v") ;;
        find-links) uv_flags+=(--find-links "$v") ;;
        constraint) uv_flags+=(--constraint "$v") ;;
        cert) export SSL_CERT_FILE="$v" ;;
      esac
    done
  done < <(if [ -n "$pip_config" ]; then cat "$pip_config"; rm -f "$pip_config"
           else "$py" -m pip config list 2>/dev/null; fi || true)
  pip_config=""
}
# requirements.lock: the demo's install (the package with its ROS extra) pinned, every
# wheel named up front: uv then fetches them all at once instead of finding each level
# of ROS's dependency tree one after another (1-4 s of a fresh machine's 31-38 s, 2026-12-02).
# Used while it is the lock of this setup.py (its header says which); `./dev.sh lock`
# writes it again; where it cannot be installed (another Python, an index without
# those releases) uv resolves setup.py itself.
lock=requirements.lock
lock_is_current() {
  [ -f "$lock" ] && [ "$(sed -n 's/^# setup.py sha256 //p' "$lock")" \
                      = "$(sha256sum setup.py | cut -d' ' -f1)" ]
}
stamp=.venv/.piezo_stage_install_stamp
want=$({ cat setup.py setup.cfg package.xml dev.sh; cat "$lock" 2>/dev/null || true; } \
       | sha256sum | cut -d' ' -f1)
have=$(cat "$stamp" 2>/dev/null || true)
if [ "${have%% *}" != "$want" ] || { [ "$extras" = ros,test ] && [ "${have#* }" != ros,test ]; }; then
  pip_config_to_uv
  # uv writes no bytecode unless asked (pip does): where Python will not write it either
  # (PYTHONDONTWRITEBYTECODE, as on this project's CI hosts) every process compiles
  # numpy, scipy, numba and rclpy again at each start: 4.7 s of CPU a node where 1.8 s
  # do with the bytecode (a set starts six such processes on two cores). The tests'
  # environment is compiled whole (its tools too); the others get what the package's
  # processes import, and the compiled kernels, from piezo_stage.process.warm below: about
  # half the time of compiling every module, and a first demo that does not compile
  # its kernels while it runs
  if [ "$extras" = ros,test ]; then uv_flags+=(--compile-bytecode); fi
  uv_install() {
    [ -n "$uv" ] && "$uv" pip install --quiet --python .venv/bin/python \
      --index-strategy unsafe-best-match "${uv_flags[@]}" "$@"
  }
  warm() { ( export PYTHONDONTWRITEBYTECODE=
             .venv/bin/python -m piezo_stage.process.warm "$1" >/dev/null 2>&1 ) || true; }
  if [ "$extras" = ros ] && lock_is_current && uv_install --no-deps -r "$lock" -e .; then
    :
  elif ! uv_install -e ".[$extras]"; then
    [ -n "$uv" ] && echo "dev.sh: uv could not install; pip takes over" >&2
    .venv/bin/python -m pip --version >/dev/null 2>&1 || .venv/bin/python -m ensurepip >/dev/null
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".[$extras]"
  fi
  if [ "$extras" = ros,test ]; then
    # the nv200 backend's package (and its tests): it declares Python >= 3.12 but runs
    # on 3.11 (every module imports and its tests pass here), so pip installs it past
    # that check, after the test extra, never as a dependency pip would refuse
    .venv/bin/python -m pip --version >/dev/null 2>&1 || .venv/bin/python -m ensurepip >/dev/null
    .venv/bin/python -m pip install --quiet --disable-pip-version-check \
      --ignore-requires-python "nv200==1.6.0"
  fi
  if [ "$extras" = ros ]; then
    # three processes on two cores: the stage's and identify's kernels, the inverse's,
    # the modules' bytecode (each 5-8 s alone on a 2-core host, 2026-12-02)
    echo "dev.sh: compiling what the package's processes use (once per install)" >&2
    warm stage & s1=$!
    warm inverse & s2=$!
    warm modules
    wait "$s1" "$s2" || true
  fi
  echo "$want $extras" > "$stamp"
fi
# the package's own modules too, where they changed (quick when none did)
.venv/bin/python -m compileall -q -j 0 piezo_stage piezo_stage_msgs_adapters >/dev/null 2>&1 \
  || true

[ $# -gt 0 ] && shift
case "$cmd" in
  test)
    # with no test selection: every test but the real-time ones on two workers (a
    # lockstep node set waits for each sample, so a second worker's load slows it and
    # changes nothing it computes; one alone keeps a core idle), then the real-time
    # ones (marked realtime) one at a time: their timing does not survive a second
    # worker's CPU load on a 2-core machine; with them the lockstep reruns compared
    # byte for byte (marked alone: the driver's state reaches the loop nodes on its
    # own topic, a few samples ahead, which a loaded host can outrun)
    if [ $# -eq 0 ] || [ "$*" = "-q" ]; then
      # (each phase ends with its 15 slowest tests: where the suite's time goes)
      .venv/bin/python -m pytest "$@" -m "not realtime and not alone" --durations=15
      exec .venv/bin/python -m pytest "$@" -m "realtime or alone" -n 0 --durations=15
    fi
    exec .venv/bin/python -m pytest "$@" ;;
  demo) exec .venv/bin/piezo-stage demo "$@" ;;
  lock)
    # requirements.lock from setup.py (after a change of its requirements): the package
    # with its ROS extra, resolved for Python >= 3.11 on every platform, pinned
    [ -n "$uv" ] || { echo "dev.sh: error: lock needs uv" >&2; exit 2; }
    [ ${#uv_flags[@]} -gt 0 ] || pip_config_to_uv
    tmp=$(mktemp "$lock.XXXXXX")
    { echo "# The demo's install pinned: ./dev.sh installs it while this is the lock of"
      echo "# setup.py below; written by ./dev.sh lock (uv pip compile of -e .[ros])."
      echo "# setup.py sha256 $(sha256sum setup.py | cut -d' ' -f1)"
      printf -- '-e .[ros]\n' | "$uv" pip compile --quiet --universal --python-version 3.11 \
        --index-strategy unsafe-best-match "${uv_flags[@]}" --no-emit-package piezo-stage \
        --no-header --no-annotate -
    } > "$tmp" || { rm -f "$tmp"; echo "dev.sh: error: uv could not resolve setup.py" >&2
                    exit 1; }
    mv "$tmp" "$lock"
    echo "$lock: $(grep -c '==' "$lock") pins" ;;
  *)    exec .venv/bin/piezo-stage "$cmd" "$@" ;;
esac
