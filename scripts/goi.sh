#!/usr/bin/env bash
# Set up goi on a fresh machine (first run only), then run `goi` with the given arguments.
# `goi view` needs the view extra (viser): installed on its first use.
if [ "${1:-}" = view ] && [ -z "${GOI_EXTRAS:-}" ]; then GOI_EXTRAS="[view]"; fi
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec "$VENV/bin/goi" "$@"
