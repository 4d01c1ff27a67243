#!/usr/bin/env bash
# The one test command: set up (idempotent), then lint, type-check and run every test.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
echo "== ruff"; ruff check fleetctl tests benchmarks e2e
echo "== mypy"; mypy
echo "== pytest"; pytest -q -ra "$@"
