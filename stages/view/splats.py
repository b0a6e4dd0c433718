"""The scene as the browser draws it: splats (centre, covariance, degree-0 colour, opacity),
sent in chunks of nearby Gaussians, and the colours of the highlight modes.

Arrays in, arrays out. A highlight changes the colours of the chunks that hold selected
Gaussians and nothing else, so a small object costs a chunk or two on the wire (about 1 MiB
each), not the scene; the chunks follow a Morton order of the centres, which keeps an object's
Gaussians in few chunks whatever order the PLY holds them in.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from stages.scene.gaussians import Gaussians
from stages.scene.rotation import quats_to_rotmats

#: Gaussians per chunk: 32 bytes each on the wire, so 1 MiB a chunk.
CHUNK = 32768
#: The highlight modes: tint (the selection recoloured), isolate (only the selection drawn),
#: hide (the scene without the selection), heat (every Gaussian coloured by its score).
MODES = ("tint", "isolate", "hide", "heat")
#: How much of the tint colour a selected splat takes (the rest is its own colour, so the
#: object stays recognisable).
TINT_SHARE = 0.65


@dataclass
class Splats:
    """The Gaussians the browser is sent, in sending order."""

    index: np.ndarray  # [S] int64: scene index of each splat (Morton order of the centres)
    centers: np.ndarray  # [S, 3] float32
    covariances: np.ndarray  # [S, 3, 3] float32
    rgbs: np.ndarray  # [S, 3] float32 in 0..1
    opacities: np.ndarray  # [S, 1] float32 in 0..1
    n_scene: int  # Gaussians in the scene (S < n_scene when the scene was too big to send whole)

    @property
    def count(self) -> int:
        return int(self.index.shape[0])

    def chunks(self, size: int = CHUNK) -> list[slice]:
        return [slice(i, min(i + size, self.count)) for i in range(0, self.count, size)]


def covariances(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """[N, 3, 3] world covariances R diag(s^2) R^T from unit quaternions [N, 4] (w, x, y, z)
    and standard deviations [N, 3]."""
    R = quats_to_rotmats(np.asarray(quats, np.float64))
    s2 = np.asarray(scales, np.float64) ** 2
    return np.einsum("nij,nj,nkj->nik", R, s2, R).astype(np.float32)


def importance(g: Gaussians) -> np.ndarray:
    """[N] how much a Gaussian shows: opacity times its largest cross-section (the two largest
    standard deviations). The most important are sent first when a scene is too big."""
    s = np.sort(np.asarray(g.scales, np.float64), axis=1)
    return np.asarray(g.opacities, np.float64) * s[:, 1] * s[:, 2]


def morton_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """[N] int64: the permutation that sorts points [N, 3] along a Z-order curve of a 2^bits
    grid over their bounds (stable: ties keep their order)."""
    p = np.asarray(points, np.float64)
    lo, hi = p.min(0), p.max(0)
    q = ((p - lo) / np.maximum(hi - lo, 1e-12) * (2**bits - 1)).astype(np.int64)
    code = np.zeros(p.shape[0], np.int64)
    for b in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> b) & 1) << (3 * b + axis)
    return np.argsort(code, kind="stable")


def scene_splats(g: Gaussians, max_splats: int) -> Splats:
    """The splats of a scene: every valid Gaussian, or the `max_splats` most important of
    them when there are more (see `importance`)."""
    valid = np.flatnonzero(np.asarray(g.valid, bool) if g.valid.size else np.ones(g.count, bool))
    if valid.size > max_splats:
        imp = importance(g)[valid]
        keep = np.argsort(-imp, kind="stable")[:max_splats]
        valid = np.sort(valid[keep])
    idx = valid[morton_order(g.means[valid])] if valid.size else valid
    return Splats(
        idx.astype(np.int64),
        np.ascontiguousarray(g.means[idx], np.float32),
        covariances(g.quats[idx], g.scales[idx]),
        g.colors_dc()[idx].astype(np.float32),
        np.asarray(g.opacities[idx], np.float32)[:, None],
        g.count,
    )


def highlighted(
    rgbs: np.ndarray, opacities: np.ndarray, selected: np.ndarray, mode: str, color: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The colours [S, 3] and opacities [S, 1] of splats whose selection is `selected` [S] bool:
    tint mixes the selected ones with `color`, hide makes them transparent; isolate draws the
    selection alone (a node of its own), so the scene's splats are unchanged here."""
    rgb, op = rgbs.copy(), opacities.copy()
    if mode == "tint":
        tint = np.asarray(color, np.float32)
        rgb[selected] = (1 - TINT_SHARE) * rgb[selected] + TINT_SHARE * tint
    elif mode == "hide":
        op[selected] = 0.0
    elif mode != "isolate":
        raise ValueError(f"unknown highlight mode {mode!r}")
    return rgb, op


#: Heat mode's colour map, from a score just above 0 to 1 (the answer's cut in the middle,
#: yellow): blue, cyan, yellow, orange, red, linearly between them.
HEAT_STOPS = np.array(
    [[0.15, 0.25, 0.9], [0.0, 0.75, 0.9], [1.0, 0.9, 0.1], [1.0, 0.5, 0.0], [0.85, 0.0, 0.0]],
    np.float32,
)
#: In heat mode a Gaussian that scores 0 keeps this share of its own colour's brightness, in
#: grey: the room stays readable around the scores.
HEAT_GREY = 0.5


def heat_colors(rgbs: np.ndarray, heat: np.ndarray) -> np.ndarray:
    """[S, 3] the colours of splats [S, 3] in heat mode, for their scores `heat` [S] in [0, 1]
    (already stretched about the cut: stages.view.selections.stretched): 0 a dim grey of the
    splat's own colour, above it the HEAT_STOPS map."""
    t = np.clip(np.asarray(heat, np.float32), 0.0, 1.0)
    x = t * (len(HEAT_STOPS) - 1)
    i = np.minimum(x.astype(np.int64), len(HEAT_STOPS) - 2)
    f = (x - i)[:, None]
    mapped = (1 - f) * HEAT_STOPS[i] + f * HEAT_STOPS[i + 1]
    grey = HEAT_GREY * np.asarray(rgbs, np.float32).mean(1, keepdims=True)
    return np.where((t > 0)[:, None], mapped, np.repeat(grey, 3, axis=1)).astype(np.float32)


def to_uint8(x: np.ndarray) -> np.ndarray:
    """0..1 floats -> uint8 as viser converts them (clip, scale, truncate)."""
    return np.clip(np.asarray(x, np.float32) * 255.0, 0, 255).astype(np.uint8)


def rgba_words(rgbs: np.ndarray, opacities: np.ndarray) -> np.ndarray:
    """[S] uint32: colour [S, 3] and opacity [S, 1] packed as the splat buffer's last word."""
    rgba = np.concatenate([to_uint8(rgbs), to_uint8(opacities)], axis=1)
    return np.ascontiguousarray(rgba).view(np.uint32)[:, 0]


def pack(centers: np.ndarray, covs: np.ndarray, rgbs: np.ndarray, opacities: np.ndarray):
    """[S, 8] uint32: viser's splat buffer (centre as 3 float32, a word the renderer uses, the
    covariance's upper triangle as 6 float16, RGBA as 4 uint8)."""
    n = centers.shape[0]
    buf = np.zeros((n, 8), np.uint32)
    buf[:, 0:3] = np.ascontiguousarray(centers, np.float32).view(np.uint32)
    tri = np.asarray(covs).reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
    buf[:, 4:7] = np.ascontiguousarray(tri, np.float16).view(np.uint32)
    buf[:, 7] = rgba_words(rgbs, opacities)
    return buf


@dataclass
class Plan:
    """What a page must be sent to show a selection in a mode."""

    chunk_words: dict[int, np.ndarray]  # chunk -> its new RGBA words [n] (only changed chunks)
    chunk_keys: list[bytes]  # what every chunk shows after the plan (compare with the next)
    scene_visible: bool  # the chunks are drawn (not in isolate mode)
    overlay: np.ndarray  # [k] scene indices drawn by a node of their own (isolate: the
    #                      selection; tint: selected Gaussians the browser was not sent)
    overlay_tinted: bool


def plan(
    splats: Splats,
    chunks: list[slice],
    shown: list[bytes],
    selected: np.ndarray | None,
    mode: str,
    color: np.ndarray,
    heat: np.ndarray | None = None,
) -> Plan:
    """The chunks to resend (those whose colours change from `shown`, what each chunk shows
    now) to show `selected` [G] bool (None: nothing) in `mode`; heat mode colours every
    splat by `heat` [G] in [0, 1] (None: the selection as 0 / 1)."""
    if mode not in MODES:
        raise ValueError(f"unknown highlight mode {mode!r}")
    sel_s = np.zeros(splats.count, bool) if selected is None else selected[splats.index]
    color = np.asarray(color, np.float32)
    heat_s = None
    if mode == "heat":
        heat_s = to_uint8(sel_s if heat is None else np.asarray(heat)[splats.index])
    words: dict[int, np.ndarray] = {}
    keys: list[bytes] = []
    for i, c in enumerate(chunks):
        s = sel_s[c]
        recolour = mode in ("tint", "hide") and s.any()
        key = b"base"
        if recolour:
            key = mode.encode() + color.tobytes() + np.packbits(s).tobytes()
        elif heat_s is not None:  # every chunk, by its splats' scores
            key = b"heat" + hashlib.blake2b(heat_s[c].tobytes(), digest_size=16).digest()
        keys.append(key)
        if key != shown[i]:
            rgb, op = splats.rgbs[c], splats.opacities[c]
            if recolour:
                rgb, op = highlighted(rgb, op, s, mode, color)
            elif heat_s is not None:
                rgb = heat_colors(rgb, heat_s[c].astype(np.float32) / 255.0)
            words[i] = rgba_words(rgb, op)
    overlay = np.zeros(0, np.int64)
    if selected is not None and mode == "isolate":
        overlay = np.flatnonzero(selected)
    elif selected is not None and mode == "tint":
        unsent = selected.copy()
        unsent[splats.index] = False
        overlay = np.flatnonzero(unsent)
    return Plan(words, keys, mode != "isolate", overlay, mode == "tint")
