"""`python -m stages.testing.models --bundle OUT`: the random-weight bundle for trying the
RES-index paths, labelled as random wherever its name shows."""

import json
import subprocess
import sys

import pytest

from stages.models.bundle import load_bundle

pytest.importorskip("transformers")


@pytest.mark.slow
def test_the_random_bundle_is_a_grounded_sam_labelled_random(tmp_path):
    out = tmp_path / "random"
    cmd = [sys.executable, "-m", "stages.testing.models", "--bundle", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith(f"bundle (RANDOM weights, its masks mean nothing): {out}\n")
    b = load_bundle(out)
    assert b.has_res and b.manifest["name"].count("RANDOM-WEIGHTS") == 2
    assert "grounded" in json.loads((out / "manifest.json").read_text())
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode == 2 and "--force" in again.stderr  # never written over silently
