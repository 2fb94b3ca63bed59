#!/usr/bin/env bash
# The whole test suite: set up (venv, packages, a headless browser for the report test, a PostgreSQL server
# for the archive tests), then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Debian packages the tests use: chromium (the report in a browser), postgresql (the site archive's server)
need=()
command -v chromium >/dev/null 2>&1 || need+=(chromium)
compgen -G "/usr/lib/postgresql/*/bin/pg_ctl" >/dev/null || need+=(postgresql)
if [ "${#need[@]}" -gt 0 ] && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null) \
    || echo "setup: could not install ${need[*]}; the tests that need them will be skipped, saying why" >&2
fi
# One pytest worker per core (pytest-xdist; docs/decisions/0058): the jobs the tests run are mostly one thread each,
# so two workers on CI's two cores halve the suite's time. Each worker keeps numpy's BLAS to one thread, or the two
# would oversubscribe the cores. CELL_TEST_WORKERS=0 runs the suite in this one process.
workers=${CELL_TEST_WORKERS:-$(nproc 2>/dev/null || echo 1)}
par=()
if [ "$workers" -gt 0 ]; then
  par=(-n "$workers" --dist load)
  export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
fi
set +e
.venv/bin/python -m pytest "${par[@]}" "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "test.sh: pytest collected no tests: that is a failure" >&2
fi
exit "$rc"
