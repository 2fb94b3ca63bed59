#!/usr/bin/env bash
# Hardware-in-the-loop tests of the robot side against URSim (default) or a real UR (CELL_UR_HOST=<robot ip>).
#   bash scripts/hil.sh            # starts URSim (docker compose), waits for it, runs tests/hil, leaves URSim running
#   CELL_UR_HOST=192.168.1.10 CELL_UR_ALLOW_MOTION=1 bash scripts/hil.sh   # a real robot (no container)
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/setup.sh
if [ -z "${CELL_UR_HOST:-}" ]; then
  command -v docker >/dev/null || { echo "hil: docker not found: install Docker or set CELL_UR_HOST to a robot" >&2; exit 2; }
  docker compose -f docker/ursim/compose.yaml up -d
  export CELL_UR_HOST=127.0.0.1 CELL_URSIM=1 CELL_UR_ALLOW_MOTION=1
  export CELL_UR_MODEL="${CELL_UR_MODEL:-ur10e}"
  echo "hil: waiting for URSim's dashboard on 127.0.0.1:29999 ..."
  for _ in $(seq 1 120); do
    if .venv/bin/python -c "from drivers.ur_dashboard import Dashboard; Dashboard('127.0.0.1').__enter__().close()" 2>/dev/null; then break; fi
    sleep 2
  done
fi
exec .venv/bin/python -m pytest -m hil tests/hil -v -p no:cacheprovider "$@"
