#!/usr/bin/env bash
# Set up a fresh machine: a virtual environment in .venv with the CPU build of torch first
# (torch==2.13.0 is a CPU wheel that pip finds on local disk; a plain `pip install torch`
# would fetch a multi-GB CUDA build), then the package in editable mode with its dev extras.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
. .venv/bin/activate
if ! python -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '2.13.0')" 2>/dev/null; then
  python -m pip install -q torch==2.13.0
fi
python -m pip install -q -e '.[dev]'
# PostgreSQL's server programs, for the multi-worker Optuna tests (tests/pg.py starts a
# throw-away cluster); a no-op when installed. Without them those tests fail and say why.
bash scripts/postgres.sh || echo "warning: PostgreSQL is missing; the PostgreSQL tests will fail" >&2
# A Compose client, for the test that validates docker/compose.yaml (no engine needed).
bash scripts/compose.sh || echo "warning: no Compose client; tests/test_docker.py will fail" >&2
echo "setup done: $(python -c 'import torch; print("torch", torch.__version__)')"
