#!/usr/bin/env bash
# The main job on the simulated cell: set up, then run the example inspection end to end.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/cell run examples/bracket/job.toml --yes "$@"
