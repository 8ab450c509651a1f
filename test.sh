#!/usr/bin/env bash
# The whole test suite, in both Pythons (README "Run the tests"):
#   1. the development venv: core, filters, CLI, and the ParaView tests, which start Debian's
#      pvpython / pvbatch / paraview (under xvfb-run) as subprocesses;
#   2. Debian's ParaView Python (numpy 1.24, numba 0.56, scipy 1.10, ParaView's VTK 9.2): the core
#      and filter tests again, with this checkout made importable by plugin/shim.
# Both load the kernels ./setup.sh compiled into the user's kernel cache (README "The first
# run"), as every pvpython and pvbatch the tests start does: each Python compiles once.
# Extra arguments go to both pytest runs (e.g. -k mvc).
set -euo pipefail
cd "$(dirname "$0")"
./setup.sh

echo "== tests in the venv ($(.venv/bin/python --version)) =="
.venv/bin/python -m pytest -q "$@"

echo "== tests in Debian's ParaView Python ($(/usr/bin/python3 --version)) =="
PYTHONPATH="$PWD/plugin/shim" /usr/bin/python3 -m pytest -q -p no:cacheprovider -m "not paraview" "$@"
