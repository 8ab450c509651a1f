#!/usr/bin/env bash
# Installs what muscle-mss needs on a Debian 12 machine (run as root), skipping what is there:
#   - Debian's ParaView 5.11 with its Python packages (pvpython, pvbatch, paraview; numba 0.56,
#     numpy 1.24, scipy 1.10), pytest for that Python, xvfb for the headless GUI, Open MPI;
#   - the development venv .venv with this package (editable) and its test extra;
#   - the numeric kernels compiled for the venv and for Debian's Python (the one pvpython and
#     pvbatch run), both at once: 2-3 minutes the first time, a second or two when compiled.
# ./demo.sh and ./test.sh call it; it is safe to run again.
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

if ! .venv/bin/python -c "import importlib.metadata as m, muscle_mss.filters, pyvista, pytest
m.version('tbb')" >/dev/null 2>&1; then
  echo "setup: creating .venv with muscle-mss and its test extra" >&2
  python3 -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
fi

# Each Python keeps its kernels in a cache folder of its own (README "The first run").
.venv/bin/python -m muscle_mss.filters.warm_up &
venv_warm_up=$!
PYTHONPATH="$PWD/plugin/shim" /usr/bin/python3 -m muscle_mss.filters.warm_up
wait "$venv_warm_up"
