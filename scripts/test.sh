#!/usr/bin/env bash
# The one test command: set up (idempotent), then lint, type-check and run every test.
#
# With no arguments, two pytest stages, so that the image build overlaps the tests that do
# not need it (the CI run must stay under 40 minutes; on a fresh 2-core machine the build
# is ~7 min, mostly debootstrap's downloads, and the suite ~31 min run serially):
#   1. while `fleetctl build` runs in the background: ruff, mypy, and every test with none of
#      the markers below (~3,000 unit and loopback tests, ~4 min; they ran beside the docker
#      e2e run without a failure when the suite was tried on two workers);
#   2. after the build: the tests that need the images, Chromium, a ROS graph, network
#      namespaces or a quiet machine (markers docker, browser, ros, netns, slow), serially:
#      their timed steps failed when they shared the two cores (README, "Tests").
# With arguments (`bash scripts/test.sh tests/client -k dialer`), one pytest run of exactly
# those, after the build.
set -euo pipefail
cd "$(dirname "$0")/.."
stamp() { date -u +%T; }
echo "== setup ($(stamp))"
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
# A whole-run deadline (default 45 min): a hang ends red, with the stacks faulthandler
# printed and pytest's summary after the SIGINT, not silent at the CI's limit.
deadline=$(( $(date +%s) + ${FLEETCTL_TEST_DEADLINE_S:-2700} ))
left() { echo $(( deadline - $(date +%s) > 60 ? deadline - $(date +%s) : 60 )); }
# The 30 slowest steps of each stage are listed at its end.
run_pytest() { timeout --signal=INT --kill-after=60 "$(left)" pytest -q -ra --durations=30 "$@"; }

build_pid=""
build_log="$(mktemp -t fleetctl-build.XXXXXX)"
# setsid: the build and its docker children are one process group, stopped together when a
# stage fails first.
stop_build() { if [ -n "$build_pid" ]; then kill -- "-$build_pid" 2>/dev/null || true; fi; }
trap 'stop_build; rm -f "$build_log"' EXIT
if docker info >/dev/null 2>&1; then
  # The docker-marked tests run against the project's images (layers are cached, so only
  # changed code is rebuilt). Its log is printed when it ends.
  echo "== fleetctl build, in the background ($(stamp))"
  setsid fleetctl build >"$build_log" 2>&1 &
  build_pid=$!
fi
wait_build() {
  [ -n "$build_pid" ] || return 0
  local code=0
  wait "$build_pid" || code=$?
  build_pid=""
  echo "== fleetctl build ended with $code ($(stamp)); its log:"
  cat "$build_log"
  return "$code"
}

echo "== ruff ($(stamp))"; ruff check fleetctl tests benchmarks e2e
echo "== mypy ($(stamp))"; mypy
MARKED="docker or browser or ros or netns or slow"
if [ "$#" -eq 0 ]; then
  echo "== pytest, stage 1: tests without the markers $MARKED ($(stamp))"
  run_pytest -m "not ($MARKED)"
  wait_build
  echo "== pytest, stage 2: $MARKED, serially ($(stamp))"
  run_pytest -m "$MARKED"
else
  wait_build
  echo "== pytest $* ($(stamp))"
  run_pytest "$@"
fi
echo "== done ($(stamp))"
