#!/usr/bin/env bash
# Set up goi on a fresh machine (first run only), then run `goi` with the given arguments.
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec "$VENV/bin/goi" "$@"
