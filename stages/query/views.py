"""Which views a RES model runs on in the lifted mode, as pure math.

A model costs seconds per view on a CPU, so it runs on K views, chosen one at a time to cover
the provisional selection S (the Gaussians the query currently answers) from different sides:

    v* = argmax_v  sum_{i in S} min(vis_v[i], max(0, cover - E_i))

with vis_v[i] Gaussian i's blend weight in view v (pixels' worth) and E_i what the views chosen
so far already show of it. Capping each Gaussian's gain at `cover` makes the objective
submodular: once a part of S is seen enough, views that show it again gain nothing, so the next
view looks at S from another side. When S is covered everywhere, the views that add the most
log-visibility (diminishing, never saturating) break the tie.

On a RES index that grows (stages.query.lift_answer), the views are also chosen apart:

    v* = argmax_v  g_v / max_u g_u + APART * d_v / max_u d_u

with g_v the gain above (the capped coverage, or the log gain once S is covered) and d_v the
pose distance (`pose_distance`) from view v to the nearest view already lifted: views that see
the selection from sides not yet seen out-vote a RES's errors, which repeat in neighbouring
views. On the dev room's SAM masks, 8 views so chosen gave test mIoU 0.823 / 0.840
(res-sam/, res-sam-correlated/, field-free) against 0.817 / 0.843 by coverage alone, and
16 views 0.885 / 0.886 against 0.877 / 0.882 (docs/benchmarks.md, #39: APART = 1, the two
terms weighed alike, was not tuned; 0.25 to 0.75 gave 0.804 to 0.848 at 8 views).

The size of a view's mask plays no part. The paper's rule of taking the largest masks is
exactly wrong for a RES that adds a big distractor (the sofa under the teddy bear): the
distractor makes those masks the largest.
"""

from __future__ import annotations

import numpy as np

#: Pixels' worth of blend weight after which a Gaussian of S counts as covered.
COVER = 3.0
#: Weight of a view's distance from the views lifted against its gain (`next_view_apart`).
APART = 1.0


def pose_distance(centers: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """[V, V] distance of two views' poses: their centres' distance (centers [V, 3]) in units
    of the views' spread (the median distance to their mean), plus 1 - cos of the angle
    between their viewing directions (axes [V, 3], unit)."""
    spread = float(np.median(np.linalg.norm(centers - centers.mean(0), axis=1)))
    d = np.linalg.norm(centers[:, None] - centers[None], axis=2) / (spread if spread > 0 else 1.0)
    return d + np.clip(1.0 - axes @ axes.T, 0.0, 2.0)


def provisional(entry_scores: np.ndarray, entry: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """[G] bool: the Gaussians whose entry is on the positive side of the plane (entry_scores
    [N], e.g. the fixed-threshold plane before any RES mask); when none is, those of the best
    scoring entry among the field's seen Gaussians, so the choice always has a target."""
    pos = entry_scores > 0
    if not pos[entry[seen]].any():
        present = np.unique(entry[seen])
        if present.size == 0:
            return np.zeros(entry.shape, bool)
        pos = entry_scores >= entry_scores[present].max()
    return seen & pos[entry]


def next_view(
    visibility: list[np.ndarray], S: np.ndarray, E: np.ndarray, cover: float = COVER
) -> int:
    """Index of the candidate view (visibility [V] of [G] arrays) that adds the most capped
    coverage of S [G] bool given what E [G] already holds; ties and a covered S go to the
    largest log-visibility gain, then to the first candidate."""
    need = np.maximum(0.0, cover - E[S])  # [|S|]
    capped = np.array([np.minimum(v[S], need).sum() for v in visibility])
    base = np.log1p(E[S])
    logg = np.array([(np.log1p(E[S] + v[S]) - base).sum() for v in visibility])
    if capped.max(initial=0.0) > 1e-9:
        # the log gain only separates views whose capped gains are (nearly) equal
        scale = 1e-6 * capped.max() / max(float(logg.max(initial=0.0)), 1e-30)
        return int(np.argmax(capped + scale * logg))
    return int(np.argmax(logg))


def next_view_apart(
    visibility: list[np.ndarray],
    S: np.ndarray,
    E: np.ndarray,
    apart: np.ndarray | None,
    cover: float = COVER,
    weight: float = APART,
) -> int:
    """Index of the candidate view that best adds coverage of S from a side not yet seen (see
    the module doc): `apart` [V] each candidate's pose distance to the nearest view lifted
    (None before any, when the gain alone decides); ties go to the first candidate."""
    need = np.maximum(0.0, cover - E[S])  # [|S|]
    gain = np.array([np.minimum(v[S], need).sum() for v in visibility])
    if gain.max(initial=0.0) <= 1e-9:  # S covered everywhere: the log-visibility gain
        base = np.log1p(E[S])
        gain = np.array([(np.log1p(E[S] + v[S]) - base).sum() for v in visibility])
    score = gain / max(float(gain.max(initial=0.0)), 1e-30)
    if apart is not None and apart.max(initial=0.0) > 0:
        score = score + weight * apart / apart.max()
    return int(np.argmax(score))
