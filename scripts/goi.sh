#!/usr/bin/env bash
# Set up goi on a fresh machine (first run only), then run `goi` with the given arguments.
# `goi view` needs the view extra (viser), `goi export-model` the export extra (transformers):
# each is installed on the command's first use.
if [ -z "${GOI_EXTRAS:-}" ]; then
  case "${1:-}" in
    view) GOI_EXTRAS="[view]" ;;
    export-model) GOI_EXTRAS="[export]" ;;
  esac
fi
source "$(dirname "${BASH_SOURCE[0]}")/setup.sh"
exec "$VENV/bin/goi" "$@"
