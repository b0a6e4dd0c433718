"""Images and masks on disk: sizes read from headers, decoding with a size limit, PNG masks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stages.core.errors import GoiError
from stages.core.files import regular_file

#: Larger images are refused before decoding: a 100k x 100k PNG would need 30 GB.
MAX_IMAGE_PIXELS = 100_000_000


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header, without decoding; None for other formats."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        if head[:2] != b"\xff\xd8":
            return None
        f.seek(2)
        while True:  # walk the JPEG segments to the first start-of-frame
            marker = f.read(2)
            if len(marker) < 2 or marker[0] != 0xFF:
                return None
            if 0xC0 <= marker[1] <= 0xCF and marker[1] not in (0xC4, 0xC8, 0xCC):
                seg = f.read(7)
                if len(seg) < 7:
                    return None
                return int.from_bytes(seg[5:7], "big"), int.from_bytes(seg[3:5], "big")
            size = f.read(2)
            if len(size) < 2:
                return None
            f.seek(int.from_bytes(size, "big") - 2, 1)


def _quiet_cv2() -> Any:
    """cv2, with its own log silenced: a damaged PNG makes OpenCV print lines of its own to
    stderr beside goi's one error line; goi reports the failure itself."""
    import cv2

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    return cv2


def _imread(path: Path, what: str, flags: int | None = None) -> np.ndarray:
    """The image at `path` as cv2.imread gives it (`flags`: IMREAD_UNCHANGED unless given),
    its file and size checked first."""
    cv2 = _quiet_cv2()
    regular_file(path, what)
    try:
        size = image_size(path)
    except OSError as e:
        raise GoiError(f"{path}: cannot read {what} ({e.strerror or e})") from None
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise GoiError(
            f"{path}: {what} is {size[0]}x{size[1]} pixels; goi reads images of up to "
            f"{MAX_IMAGE_PIXELS // 1_000_000} megapixels"
        )
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if flags is None else flags)
    if img is None:
        raise GoiError(f"{path}: cannot read {what} (not a PNG/JPEG/..., or damaged)")
    return img


def read_rgb(path: Path, width: int | None = None, height: int | None = None) -> np.ndarray:
    import cv2

    img = _imread(path, "image")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)
    if width is not None and (img.shape[1], img.shape[0]) != (width, height):
        raise GoiError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but its camera says {width}x{height}"
        )
    return img


def read_mask(path: Path) -> np.ndarray:
    """A binary mask image (any bit depth, grey or colour) -> [H, W] bool, non-zero = in."""
    img = _imread(path, "mask image")
    if img.ndim == 3:
        img = img[:, :, :3].max(axis=2)
    # 0/255 (or 0/65535) masks split at half range; 0/1 masks at zero; float images at 0.5
    if img.dtype.kind not in "ui":
        return np.asarray(img > 0.5)
    half = np.iinfo(img.dtype).max // 2 if img.max() > 1 else 0
    return np.asarray(img > half)
