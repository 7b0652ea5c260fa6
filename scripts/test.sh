#!/usr/bin/env bash
# Sets everything up, lints (ruff, settings in pyproject.toml), then runs the default (fast) test suite.
# Extra args go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q "$@"
