"""Which views a RES model runs on in the lifted mode, as pure math.

A model costs seconds per view on a CPU, so it runs on K views, chosen one at a time to cover
the provisional selection S (the Gaussians the query currently answers) from different sides:

    v* = argmax_v  sum_{i in S} min(vis_v[i], max(0, cover - E_i))

with vis_v[i] Gaussian i's blend weight in view v (pixels' worth) and E_i what the views chosen
so far already show of it. Capping each Gaussian's gain at `cover` makes the objective
submodular: once a part of S is seen enough, views that show it again gain nothing, so the next
view looks at S from another side. When S is covered everywhere, the views that add the most
log-visibility (diminishing, never saturating) break the tie.

The size of a view's mask plays no part. The paper's rule of taking the largest masks is
exactly wrong for a RES that adds a big distractor (the sofa under the teddy bear): the
distractor makes those masks the largest.
"""

from __future__ import annotations

import numpy as np

#: Pixels' worth of blend weight after which a Gaussian of S counts as covered.
COVER = 3.0


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
