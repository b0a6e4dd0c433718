"""Feature files made by other tools: `<view>.npy` [D, h, w] or the authors' APE `<view>.pt`
(float16 [D, H, W], loaded as plain tensors only), and their resampling to goi's grid."""

from __future__ import annotations

import pickle
import warnings
import zipfile
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError

MAX_FEATURE_VALUES = 1 << 31  # one map of more than 2^31 values (8 GiB) is refused


def find_feature_file(src: Path, view: str, image: str | None) -> Path | None:
    names = [view, *([Path(image).name] if image else [])]
    for base in names:
        for ext in (".npy", ".pt"):
            cand = src / f"{base}{ext}"
            if cand.is_file():
                return cand
    return None


def load_feature_file(path: Path) -> np.ndarray:
    """A [D, h, w] map from `.npy` or from the authors' APE `.pt` (a tensor, nothing else)."""
    if path.suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False, mmap_mode="r")
        except (ValueError, EOFError) as e:  # EOFError: an empty or cut-off file
            raise GoiError(f"{path}: not a plain numeric .npy array ({e})") from None
        except OSError as e:
            raise GoiError(f"{path}: cannot read ({e})") from None
    else:
        import torch

        try:
            with warnings.catch_warnings():  # torch warns about the file's pickle protocol
                warnings.simplefilter("ignore")
                t = torch.load(path, map_location="cpu", weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise GoiError(f"{path}: refused: not a plain tensor file ({first[:160]})") from None
        if not isinstance(t, torch.Tensor):
            raise GoiError(f"{path}: holds a {type(t).__name__}, expected one [D, H, W] tensor")
        arr = t.float().numpy()
    if arr.ndim != 3 or 0 in arr.shape:
        raise GoiError(f"{path}: shape {tuple(arr.shape)}, expected [D, h, w] of non-zero sizes")
    if arr.dtype.kind not in "fiu":
        raise GoiError(f"{path}: dtype {arr.dtype} is not numeric")
    if int(np.prod(arr.shape, dtype=np.int64)) > MAX_FEATURE_VALUES:
        raise GoiError(f"{path}: shape {tuple(arr.shape)} is too large")
    try:
        return np.asarray(arr, dtype=np.float32)
    except (ValueError, OSError) as e:  # a memory-mapped file cut short
        raise GoiError(f"{path}: cannot read the array ({e})") from None


def to_float16(hwd: np.ndarray) -> np.ndarray:
    """[h, w, D] as float16 without overflow: a cell whose values exceed float16's range is
    scaled down by a power of two first, which changes no cosine (goi compares features only
    by cosine) and leaves every other cell's bits as a plain cast gives them."""
    peak = np.abs(hwd).max(axis=2, keepdims=True)  # [h, w, 1]
    limit = np.float32(np.finfo(np.float16).max / 2)
    if not (peak > limit).any():
        return hwd.astype(np.float16)
    shift = np.where(peak > limit, np.ceil(np.log2(peak / limit)), 0).astype(np.int32)
    return np.ldexp(hwd, -shift).astype(np.float16)


def resample(chw: np.ndarray, max_side: int) -> np.ndarray:
    """[D, h, w] -> [h', w', D] with max(h', w') <= max_side (area average, aspect kept)."""
    import cv2

    d, h, w = chw.shape
    hwd = np.ascontiguousarray(chw.transpose(1, 2, 0))
    scale = max_side / max(h, w)
    if scale >= 1:
        return hwd
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    # cv2 resizes at most 512 channels at once.
    parts = [
        cv2.resize(hwd[:, :, c : c + 256], (nw, nh), interpolation=cv2.INTER_AREA)
        for c in range(0, d, 256)
    ]
    parts = [p[:, :, None] if p.ndim == 2 else p for p in parts]
    return np.concatenate(parts, axis=2)
