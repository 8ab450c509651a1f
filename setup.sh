#!/usr/bin/env bash
# Installs what muscle-mss needs on a Debian 12 machine (run as root), skipping what is there:
#   - Debian's ParaView 5.11 with its Python packages (pvpython, pvbatch, paraview; numba 0.56,
#     numpy 1.24, scipy 1.10), pytest for that Python, xvfb for the headless GUI, Open MPI;
#   - the development venv .venv with this package (editable) and its test extra;
#   - the numeric kernels compiled (README "The first run"), into the user's kernel cache that
#     every later run and the tests load them from: the venv's first (the demo needs only
#     those), then Debian's Python's (the one pvpython and pvbatch run). One after the other:
#     at once on two cores the two slowed each other by 60-80 % (two warm-ups of the
#     default settings side by side did not, later: docs/performance.md).
# ./demo.sh calls it as `./setup.sh --background`: it compiles nothing before it returns (the
# demo compiles the default settings' kernels, which are all it needs, in a second process while
# it writes its scene and prepares its first time point); once those are compiled, the venv's
# other kernels, then Debian's Python's, compile in the background at the lowest priority (on
# the cores the demo leaves free; with one core, before the demo), logged to
# .venv/warm-up.log. ./test.sh calls it plainly and so waits for all of them, a background
# compile included (a lock: .venv/warm-up.lock).
# Safe to run again; silent when everything is there.
set -euo pipefail
cd "$(dirname "$0")"

need_apt=0
command -v pvpython >/dev/null 2>&1 || need_apt=1
command -v xvfb-run >/dev/null 2>&1 || need_apt=1
command -v mpiexec >/dev/null 2>&1 || need_apt=1
/usr/bin/python3 -c "import numba, scipy, pytest" >/dev/null 2>&1 || need_apt=1
python3 -m venv --help >/dev/null 2>&1 || need_apt=1
if [ "$need_apt" = 1 ]; then
  echo "setup: installing Debian's ParaView 5.11 and friends with apt-get" >&2
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    paraview python3-paraview python3-numba python3-scipy python3-pytest \
    xvfb xauth openmpi-bin python3-venv python3-pip >/dev/null
fi

# (an install whose muscle-mss command still names a module that moved, or without the opensim
# extra of `muscle-mss import-opensim`, is installed again)
if ! .venv/bin/python -c "import importlib.metadata as m, muscle_mss.app.cli, pyvista, pytest, opensim
m.version('tbb')
assert [e.value for e in m.entry_points(group='console_scripts', name='muscle-mss')] \\
    == ['muscle_mss.app.cli:main']" >/dev/null 2>&1; then
  echo "setup: creating .venv with muscle-mss and its test and opensim extras" >&2
  python3 -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test,opensim]'
fi

# Each Python keeps its kernels in a cache folder of its own (README "The first run").
venv_warm_up=(.venv/bin/python -m muscle_mss.app.warm_up --quiet)
debian_warm_up=(env PYTHONPATH="$PWD/plugin/shim" /usr/bin/python3 -m muscle_mss.app.warm_up
                --quiet)
lock=.venv/warm-up.lock
if [ "${1:-}" = "--background" ] && [ "$(nproc)" -ge 2 ]; then
  all_warm="from muscle_mss.core import kernel_cache as k; assert k.is_warm()"
  if flock -n "$lock" true && ! { .venv/bin/python -c "$all_warm" && env \
      PYTHONPATH="$PWD/plugin/shim" /usr/bin/python3 -c "$all_warm"; } >/dev/null 2>&1; then
    echo "setup: the kernels the demo does not use compile in the background after its own" \
      "(.venv/warm-up.log)" >&2
    nohup flock "$lock" nice -n 19 bash -c "$(printf '%q ' "${venv_warm_up[@]}") --after-defaults \
&& $(printf '%q ' "${debian_warm_up[@]}")" >.venv/warm-up.log 2>&1 &
  fi   # else compiled already, or a background compile holds the lock
else
  flock "$lock" "${venv_warm_up[@]}"
  flock "$lock" "${debian_warm_up[@]}"
fi
