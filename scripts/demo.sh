#!/usr/bin/env bash
# Set up (idempotent) and run the whole fleet on this machine: `fleetctl demo`.
# Extra arguments go to `fleetctl demo` (e.g. --robots 3, --duration 60).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/fleetctl demo "$@"
