"""Quaternions (w, x, y, z) and rotation matrices: the one definition every reader and the
rasteriser's reference use (the numba projection kernel spells the same formula out inline)."""

from __future__ import annotations

import numpy as np


def quats_to_rotmats(q: np.ndarray) -> np.ndarray:
    """[N, 4] unit (w, x, y, z) -> [N, 3, 3]."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        axis=1,
    ).reshape(-1, 3, 3)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """[4] quaternion (w, x, y, z), any non-zero length -> [3, 3] rotation matrix."""
    q = np.asarray(q, np.float64)
    return quats_to_rotmats((q / np.linalg.norm(q))[None])[0]


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """[3, 3] rotation -> [4] unit quaternion (w, x, y, z) with w >= 0 (COLMAP's images.txt)."""
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])
