"""PlayCanvas's splat-transform (npm @playcanvas/splat-transform 3.7.0, MIT), the PLY reader of
SuperSplat, for the interop tests: the PLYs goi writes must read there as 3DGS scenes.

`fetch()` installs the pinned package once with npm into a cache outside the repository
($GOI_CACHE, else ~/.cache/goi; about 115 MB with its WebGPU dependency, install scripts not
run, the optional PlayCanvas engine left out) and returns its command line; the tests skip when
it cannot be had (no node or npm, no registry).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

VERSION = "3.7.0"
PACKAGE = f"@playcanvas/splat-transform@{VERSION}"
_CLI = Path("node_modules", "@playcanvas", "splat-transform", "bin", "cli.mjs")


def cache_dir() -> Path:
    root = os.environ.get("GOI_CACHE") or str(Path.home() / ".cache" / "goi")
    return Path(root) / f"splat-transform-{VERSION}"


def cached() -> Path | None:
    """The installed cli.mjs, or None."""
    cli = cache_dir() / _CLI
    return cli if cli.is_file() else None


def fetch() -> Path:
    """The cli.mjs, installed with npm first when needed. Raises RuntimeError with the reason
    when it cannot be had."""
    have = cached()
    if have is not None:
        return have
    npm = shutil.which("npm")
    if npm is None or shutil.which("node") is None:
        raise RuntimeError("node and npm are not both installed")
    d = cache_dir()
    d.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=d.parent, prefix=".splat-transform.") as t:
        # no install scripts run; the PlayCanvas engine (a peer dependency) is not needed
        flags = ["--no-save", "--ignore-scripts", "--no-audit", "--no-fund", "--legacy-peer-deps"]
        run = subprocess.run(
            [npm, "install", "--prefix", t, *flags, PACKAGE],
            capture_output=True,
            text=True,
            timeout=600,
        )
        if run.returncode != 0 or not (Path(t) / _CLI).is_file():
            raise RuntimeError(f"npm install {PACKAGE} failed: {run.stderr.strip()[-300:]}")
        if cached() is None:  # another process may have installed it meanwhile
            if d.exists():  # an unfinished copy
                shutil.rmtree(d)
            Path(t).rename(d)
            Path(t).mkdir()  # for TemporaryDirectory's clean-up
    return d / _CLI


def run(args: list[str], timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """`splat-transform ARGS` (fetched first when needed)."""
    node = shutil.which("node")
    if node is None:
        raise RuntimeError("node is not installed")
    return subprocess.run(
        [node, str(fetch()), *args], capture_output=True, text=True, timeout=timeout
    )


if __name__ == "__main__":
    try:
        print(fetch())
    except RuntimeError as e:
        print(f"splat-transform not fetched ({e}); the tests that use it skip", file=sys.stderr)
