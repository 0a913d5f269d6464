#!/usr/bin/env bash
# The crash test's long run: ROUNDS (default 100) SIGKILLs of a real echomap-server process
# during a stream of uploads, restarting it on the same SQLite file each time; prints how many
# acknowledged contributions were lost (must be 0) and the file's integrity check.
#
#   tests/crash/run.sh [ROUNDS]
set -euo pipefail
cd "$(dirname "$0")/../.."
ECHOMAP_CRASH_ROUNDS="${1:-100}" cargo test --release -q -p echomap-server --test crash \
    acknowledged_contributions_survive_sigkill -- --nocapture
