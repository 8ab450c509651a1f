#!/usr/bin/env bash
# The demo (README "Run the demo"): installs what is missing, then runs `muscle-mss demo` on the
# embedded demo thigh scene. Output folder: the first argument, default ./demo_out.
set -euo pipefail
cd "$(dirname "$0")"
./setup.sh --background
exec .venv/bin/muscle-mss demo "${1:-demo_out}"
