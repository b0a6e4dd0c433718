#!/usr/bin/env bash
# Set up goi with its development tools (first run only), then lint, type-check and test.
GOI_EXTRAS="[dev]"
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
cd "$ROOT"
"$VENV/bin/ruff" check .
"$VENV/bin/ruff" format --check .
"$VENV/bin/mypy"
"$VENV/bin/lint-imports" --no-cache
"$VENV/bin/python" -m pytest -q "$@"
