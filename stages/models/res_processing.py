"""Pre- and post-processing of the RES models, in numpy, in one place.

These are what transformers' image processors and post-processing functions do for Grounding
DINO, SAM and CLIPSeg, re-written so that running a bundle needs neither Pillow, torch nor
transformers. tests/models/test_res_processing.py holds each function to the processor's
own output (the Pillow backends, transformers' reference implementations): resizing is bit-exact
with Pillow, normalised pixels within 1e-6, boxes and scores equal, SAM's mask logits within
3e-6. Images are [H, W, 3] uint8 RGB throughout; sizes are (height, width).
"""

from __future__ import annotations

import functools
import math

import numpy as np

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# -------------------------------------------------------------------------------------------
# Pillow's resampling (libImaging/Resample.c), bit-exact for 8-bit images
# -------------------------------------------------------------------------------------------
_PRECISION_BITS = 32 - 8 - 2


def _bilinear(x: np.ndarray) -> np.ndarray:
    x = np.abs(x)
    return np.where(x < 1.0, 1.0 - x, 0.0)


def _bicubic(x: np.ndarray) -> np.ndarray:
    a = -0.5
    x = np.abs(x)
    return np.where(
        x < 1.0,
        ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0,
        np.where(x < 2.0, (((x - 5.0) * x + 8.0) * x - 4.0) * a, 0.0),
    )


_FILTERS = {"bilinear": (_bilinear, 1.0), "bicubic": (_bicubic, 2.0)}


def _coeffs(in_size: int, out_size: int, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per output pixel: the first input index, the tap count and fixed-point weights."""
    fn, support0 = _FILTERS[kind]
    scale = in_size / out_size
    filterscale = max(scale, 1.0)
    support = support0 * filterscale
    ksize = int(math.ceil(support)) * 2 + 1
    xmins = np.empty(out_size, np.int64)
    counts = np.empty(out_size, np.int64)
    kk = np.zeros((out_size, ksize), np.float64)
    for xx in range(out_size):
        center = (xx + 0.5) * scale
        xmin = max(int(center - support + 0.5), 0)  # C's cast truncates toward zero
        xmax = min(int(center + support + 0.5), in_size) - xmin
        w = fn((np.arange(xmax) + xmin - center + 0.5) / filterscale)
        total = w.sum()
        if total != 0.0:
            w = w / total
        kk[xx, :xmax] = w
        xmins[xx], counts[xx] = xmin, xmax
    one = float(1 << _PRECISION_BITS)
    fixed = np.where(kk < 0, np.trunc(-0.5 + kk * one), np.trunc(0.5 + kk * one))
    return xmins, counts, fixed.astype(np.int64)


def _resample_axis(img: np.ndarray, out_size: int, axis: int, kind: str) -> np.ndarray:
    """One separable pass over `axis` (0: vertical, 1: horizontal), rounded to 8 bits.

    int32 holds every sum exactly: a pixel (<= 255) times the weights' absolute sum (<= 1.25
    for these filters, in units of 2^22) stays below 2^31."""
    xmins, counts, kk = _coeffs(img.shape[axis], out_size, kind)
    src = np.moveaxis(img, axis, 0)
    shape = (out_size,) + src.shape[1:]
    acc = np.full(shape, 1 << (_PRECISION_BITS - 1), np.int32)
    term = np.empty(shape, np.int32)
    for t in range(kk.shape[1]):
        valid = t < counts
        idx = np.where(valid, xmins + t, 0)
        w = np.where(valid, kk[:, t], 0).astype(np.int32)
        np.multiply(src[idx], w.reshape((-1,) + (1,) * (src.ndim - 1)), out=term, dtype=np.int32)
        acc += term
    out = np.clip(acc >> _PRECISION_BITS, 0, 255).astype(np.uint8)
    return np.moveaxis(out, 0, axis)


def pil_resize(rgb: np.ndarray, size_hw: tuple[int, int], kind: str = "bilinear") -> np.ndarray:
    """`PIL.Image.resize((w, h), BILINEAR | BICUBIC)` of an [H, W, C] uint8 array, bit for bit.

    Pillow resamples in two separable passes through an 8-bit intermediate image, and a pass
    is skipped when its axis keeps its size; shrinking widens the filter (antialiasing). Pillow
    runs the vertical pass first exactly when the height shrinks and th - h < 2 (tw - w) (found
    empirically on 595 random cases, pinned by the tests)."""
    h, w = size_hw
    ih, iw = rgb.shape[:2]
    if w != iw and h < ih and (h - ih) < 2 * (w - iw):
        return np.ascontiguousarray(_resample_axis(_resample_axis(rgb, h, 0, kind), w, 1, kind))
    out = rgb
    if w != iw:
        out = _resample_axis(out, w, 1, kind)
    if h != ih:
        out = _resample_axis(out, h, 0, kind)
    return np.ascontiguousarray(out)


def _unit(rgb: np.ndarray) -> np.ndarray:
    """uint8 -> 0..1 float32 as transformers rescales: x * (1/255) in float64, then cast."""
    return (rgb.astype(np.float64) * (1 / 255)).astype(np.float32)


def normalize(rgb: np.ndarray, mean: tuple[float, ...], std: tuple[float, ...]) -> np.ndarray:
    """[H, W, 3] uint8 -> [3, H, W] float32 as transformers does it: x * (1/255) in float64,
    cast to float32, then (x - mean) / std in float32."""
    y = (_unit(rgb) - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(y.transpose(2, 0, 1))


def sigmoid(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        out: np.ndarray = 1.0 / (1.0 + np.exp(-x))
    return out.astype(np.float32)


def bilinear_resize_f32(x: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """`torch.nn.functional.interpolate(mode="bilinear", align_corners=False)` on [..., H, W]
    float32: half-pixel centres, source index clamped at 0, no antialiasing."""

    def axis(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # PyTorch computes scale * (i + 0.5) - 0.5 in float32 as one fused multiply-add (one
        # rounding). The product of two float32 numbers is exact in float64, so float64
        # arithmetic rounded once to float32 reproduces it; plain float32 arithmetic rounds
        # twice and moves the source index by up to 6e-4.
        scale = np.float64(np.float32(n_in / n_out))
        src = ((np.arange(n_out) + 0.5) * scale - 0.5).astype(np.float32)
        src = np.maximum(src, np.float32(0))
        i0 = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        lam = np.clip(src - i0.astype(np.float32), 0, 1).astype(np.float32)
        return i0, i1, lam

    x = x.astype(np.float32, copy=False)
    y0, y1, ly = axis(x.shape[-2], size_hw[0])
    x0, x1, lx = axis(x.shape[-1], size_hw[1])
    ly = ly[:, None]
    top = x[..., y0, :] * (np.float32(1) - ly) + x[..., y1, :] * ly
    return (top[..., x0] * (np.float32(1) - lx) + top[..., x1] * lx).astype(np.float32)


# -------------------------------------------------------------------------------------------
# Grounding DINO (GroundingDinoImageProcessor, post_process_grounded_object_detection)
# -------------------------------------------------------------------------------------------
def fit_shape(h: int, w: int, max_h: int, max_w: int) -> tuple[int, int]:
    """The processor's size {"max_height", "max_width"}: the largest size of the image's aspect
    ratio inside max_h x max_w (transformers' get_image_size_for_max_height_width)."""
    scale = min(max_h / h, max_w / w)
    return int(h * scale), int(w * scale)


def detector_inputs(
    rgb: np.ndarray,
    canvas_hw: tuple[int, int],
    mean: tuple[float, ...] = IMAGENET_MEAN,
    std: tuple[float, ...] = IMAGENET_STD,
) -> tuple[np.ndarray, np.ndarray]:
    """-> pixel_values [1, 3, H, W] float32 and pixel_mask [1, H, W] int64 on the fixed canvas:
    the image resized to fit it (Pillow bilinear), normalised, zero-padded at the bottom and
    right (the processor with size {"max_height": H, "max_width": W} and pad_size H x W)."""
    ch, cw = canvas_hw
    h, w = fit_shape(rgb.shape[0], rgb.shape[1], ch, cw)
    pixels = np.zeros((1, 3, ch, cw), np.float32)
    pixels[0, :, :h, :w] = normalize(pil_resize(rgb, (h, w)), mean, std)
    mask = np.zeros((1, ch, cw), np.int64)
    mask[0, :h, :w] = 1
    return pixels, mask


def detector_caption(prompt: str) -> str:
    """Grounding DINO's caption form of a prompt: lower case, ending with '.' (the phrase
    delimiter), as Grounded-SAM and GOI's code write it."""
    text = prompt.strip().lower()
    return text if text.endswith(".") else text + "."


def detections(
    logits: np.ndarray,
    boxes: np.ndarray,
    image_hw: tuple[int, int],
    box_threshold: float,
    max_boxes: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The detector's boxes for one image: logits [Q, L] (pre-sigmoid, over the prompt's
    tokens), boxes [Q, 4] (cx, cy, w, h relative to the unpadded resized image) -> boxes [K, 4]
    (x0, y0, x1, y1 in pixels of the original image) and scores [K], best first.

    A box's score is the largest token probability (post_process_grounded_object_detection);
    boxes scoring above `box_threshold` are kept, at most `max_boxes` of them."""
    scores = sigmoid(logits.astype(np.float32)).max(-1)
    cx, cy, bw, bh = (boxes[:, i].astype(np.float32) for i in range(4))
    xyxy = np.stack([cx - 0.5 * bw, cy - 0.5 * bh, cx + 0.5 * bw, cy + 0.5 * bh], -1)
    h, w = image_hw
    xyxy = xyxy * np.asarray([w, h, w, h], np.float32)
    keep = np.flatnonzero(scores > box_threshold)
    keep = keep[np.argsort(-scores[keep], kind="stable")][:max_boxes]
    return xyxy[keep].astype(np.float32), scores[keep].astype(np.float32)


# -------------------------------------------------------------------------------------------
# SAM (SamImageProcessor, SamProcessor's box coordinates, post_process_masks)
# -------------------------------------------------------------------------------------------
def sam_shape(h: int, w: int, longest: int) -> tuple[int, int]:
    scale = longest * 1.0 / max(h, w)
    return int(h * scale + 0.5), int(w * scale + 0.5)


def sam_inputs(
    rgb: np.ndarray,
    size: int,
    mean: tuple[float, ...] = IMAGENET_MEAN,
    std: tuple[float, ...] = IMAGENET_STD,
) -> np.ndarray:
    """-> pixel_values [1, 3, size, size]: the longest side resized to `size` (Pillow
    bilinear), normalised, zero-padded at the bottom and right."""
    h, w = sam_shape(rgb.shape[0], rgb.shape[1], size)
    out = np.zeros((1, 3, size, size), np.float32)
    out[0, :, :h, :w] = normalize(pil_resize(rgb, (h, w)), mean, std)
    return out


def sam_boxes(boxes_xyxy: np.ndarray, image_hw: tuple[int, int], size: int) -> np.ndarray:
    """Boxes [B, 4] in pixels of the original image -> [1, B, 4] float32 in the resized frame
    the encoder saw (SamProcessor's coordinate normalisation)."""
    h, w = image_hw
    nh, nw = sam_shape(h, w, size)
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    b = b * np.asarray([nw / w, nh / h, nw / w, nh / h])
    return b.astype(np.float32)[None]


def sam_mask_logits_reference(
    low_res: np.ndarray, image_hw: tuple[int, int], size: int
) -> np.ndarray:
    """post_process_masks without the threshold: low-resolution logits [..., s, s] -> bilinear
    to size x size, the padding cropped, bilinear to the original image -> [..., H, W]. The
    plain two-step form; `sam_mask_logits` is the fast one held equal to it."""
    h, w = sam_shape(image_hw[0], image_hw[1], size)
    m = bilinear_resize_f32(low_res, (size, size))
    m = np.ascontiguousarray(m[..., :h, :w])
    return bilinear_resize_f32(m, image_hw)


def _bilinear_matrix(n_in: int, n_out: int) -> np.ndarray:
    """[n_out, n_in] float64: `bilinear_resize_f32` along one axis as a matrix."""
    eye = np.eye(n_in, dtype=np.float32)
    return bilinear_resize_f32(eye, (n_out, n_in)).astype(np.float64)


def _taps(r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A resampling matrix [n_out, n_in] -> its non-zero columns [n_out, T] and weights."""
    t = int((r != 0).sum(axis=1).max())
    idx = np.argsort(r == 0, axis=1, kind="stable")[:, :t]
    return idx, np.take_along_axis(r, idx, axis=1).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _sam_upscale(
    s: int, image_hw: tuple[int, int], size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The two bilinear resizes and the crop between them, composed per axis into one
    [H, s] and one [W, s] matrix, as taps: (rows [H, T], their weights, columns [W, T], their
    weights). Each output reads 3 source cells an axis at SAM's sizes."""
    h, w = sam_shape(image_hw[0], image_hw[1], size)
    ry = _bilinear_matrix(h, image_hw[0]) @ _bilinear_matrix(s, size)[:h]  # [H, s]
    rx = _bilinear_matrix(w, image_hw[1]) @ _bilinear_matrix(s, size)[:w]  # [W, s]
    return (*_taps(ry), *_taps(rx))


def sam_mask_logits(low_res: np.ndarray, image_hw: tuple[int, int], size: int) -> np.ndarray:
    """`sam_mask_logits_reference` in one pass an axis: [..., s, s] -> [..., H, W].

    The reference interpolates to size x size (a million cells for SAM's 1024) before it
    crops and interpolates again; both steps are linear along each axis, so their composition
    is one resampling an axis with a few taps (cached per image size). Each output is one
    float32 sum instead of two rounded steps: equal to the reference within 1e-5 for logits of
    magnitude ~10 (tests/models/test_res_processing.py); 4.5 ms instead of 40 ms for 3 masks at
    640 x 480. Gathers and einsum, not BLAS: BLAS's threads would spin against onnxruntime's
    between SAM's runs."""
    low = np.asarray(low_res, np.float32)
    iy, wy, ix, wx = _sam_upscale(int(low.shape[-1]), (int(image_hw[0]), int(image_hw[1])), size)
    rows = np.einsum("...hts,ht->...hs", low[..., iy, :], wy)  # [..., H, s]
    out: np.ndarray = np.einsum("...hwt,wt->...hw", rows[..., ix], wx)  # [..., H, W]
    return out


# -------------------------------------------------------------------------------------------
# SAM 2 (Sam2ImageProcessor, Sam2Processor's box coordinates, post_process_masks)
# -------------------------------------------------------------------------------------------
def sam2_inputs(
    rgb: np.ndarray,
    size: int,
    mean: tuple[float, ...] = IMAGENET_MEAN,
    std: tuple[float, ...] = IMAGENET_STD,
) -> np.ndarray:
    """-> pixel_values [1, 3, size, size]: unlike SAM, SAM 2 squashes the image to the square
    (no aspect ratio kept, no padding), bilinear, then normalises.

    Sam2ImageProcessor is a torchvision backend: it resizes the uint8 image with
    `F.interpolate(mode="bilinear", antialias=True)`, whose uint8 path is Pillow's fixed-point
    filter; `pil_resize` is Pillow's, equal to it within one grey level
    (tests/models/test_sam2.py)."""
    return square_inputs(rgb, (size, size), mean, std)


def sam2_boxes(boxes_xyxy: np.ndarray, image_hw: tuple[int, int], size: int) -> np.ndarray:
    """Boxes [B, 4] in pixels of the original image -> [1, B, 4] float32 in the size x size
    frame (Sam2Processor: x scaled by size / W, y by size / H, each axis on its own)."""
    h, w = image_hw
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    b = b * np.asarray([size / w, size / h, size / w, size / h])
    return b.astype(np.float32)[None]


def sam2_mask_logits(low_res: np.ndarray, image_hw: tuple[int, int]) -> np.ndarray:
    """post_process_masks without the threshold: [..., s, s] -> bilinear (half-pixel) straight
    to the image [..., H, W] (nothing to crop: the input was not padded)."""
    return bilinear_resize_f32(np.asarray(low_res, np.float32), image_hw)


# -------------------------------------------------------------------------------------------
# CLIPSeg (ViTImageProcessor as its checkpoints configure it) and single-model RES
# -------------------------------------------------------------------------------------------
def square_inputs(
    rgb: np.ndarray, size_hw: tuple[int, int], mean: tuple[float, ...], std: tuple[float, ...]
) -> np.ndarray:
    """-> [1, 3, h, w]: the image resized to exactly size_hw (no aspect ratio kept, Pillow
    bilinear), normalised."""
    return normalize(pil_resize(rgb, size_hw), mean, std)[None]


def scores_to_mask(scores: np.ndarray, image_hw: tuple[int, int], threshold: float) -> np.ndarray:
    """Scores [h, w] -> bool [H, W]: bilinear (half-pixel) to the image, > threshold."""
    return bilinear_resize_f32(scores, image_hw) > threshold


# -------------------------------------------------------------------------------------------
# OWLv2 (the split detector: image side once, a dot product per prompt)
# -------------------------------------------------------------------------------------------
def _mirror(j: np.ndarray, n: int) -> np.ndarray:
    """scipy.ndimage's mode "mirror" (numpy's pad "reflect"): ... c b | a b c | b a ..."""
    if n == 1:
        return np.zeros_like(j)
    period = 2 * (n - 1)
    j = np.mod(j, period)
    return np.where(j < n, j, period - j)


def _owl_axis(n_in: int, n_out: int) -> np.ndarray:
    """[n_out, n_in] float64: one axis of Owlv2ImageProcessor's resize as a matrix. A Gaussian
    anti-alias with sigma (n_in / n_out - 1) / 2 when shrinking (scipy's gaussian_filter,
    truncate 4, mode mirror), then linear interpolation at half-pixel centres (ndi.zoom with
    order 1, grid_mode True, mode mirror)."""
    sigma = max(0.0, (n_in / n_out - 1) / 2)
    g = np.eye(n_in)
    if sigma > 1e-15:  # scipy skips an axis whose sigma is 0
        r = int(4.0 * sigma + 0.5)
        k = np.arange(-r, r + 1)
        w = np.exp(-0.5 * (k / sigma) ** 2)
        w /= w.sum()
        g = np.zeros((n_in, n_in))
        rows = np.arange(n_in)[:, None]
        np.add.at(g, (np.broadcast_to(rows, (n_in, k.size)), _mirror(rows + k, n_in)), w)
    src = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
    i0 = np.floor(src).astype(np.int64)
    t = src - i0
    z = np.zeros((n_out, n_in))
    rows = np.arange(n_out)
    np.add.at(z, (rows, _mirror(i0, n_in)), 1 - t)
    np.add.at(z, (rows, _mirror(i0 + 1, n_in)), t)
    out: np.ndarray = z @ g
    return out


@functools.lru_cache(maxsize=8)
def _owl_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray]:
    return _taps(_owl_axis(n_in, n_out))


def _owl_padded(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 -> the 0..1 image (float32, as the processor rescales it) on a square of
    its longest side, padded with grey 0.5 at the bottom and right [S, S, 3]."""
    x = _unit(rgb)
    h, w = x.shape[:2]
    pad = np.full((max(h, w), max(h, w), 3), 0.5, np.float32)
    pad[:h, :w] = x
    return pad


def _owl_finished(
    y: np.ndarray, pad: np.ndarray, mean: tuple[float, ...], std: tuple[float, ...]
) -> np.ndarray:
    """The resized square [size, size, 3] clipped to the padded image's range (skimage's
    clip after a warp, as the processor does) and normalised -> [1, 3, size, size]."""
    y = np.clip(y, pad.min(), pad.max())
    out = (y - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(out.transpose(2, 0, 1))[None]


def owl_inputs_reference(
    rgb: np.ndarray, size: int, mean: tuple[float, ...], std: tuple[float, ...]
) -> np.ndarray:
    """Owlv2ImageProcessor's pixels, the plain way: the 0..1 image padded to a square with grey
    0.5 at the bottom and right, resized with dense per-axis matrices (`_owl_axis`), clipped
    to the padded image's range, normalised. `owl_inputs` is the fast form held equal to it."""
    pad = _owl_padded(rgb)
    side = pad.shape[0]
    m = _owl_axis(side, size)
    y = np.einsum("oh,hwc->owc", m, pad.astype(np.float64))
    y = np.einsum("pw,owc->opc", m, y).astype(np.float32)
    return _owl_finished(y, pad, mean, std)


def owl_inputs(
    rgb: np.ndarray, size: int, mean: tuple[float, ...], std: tuple[float, ...]
) -> np.ndarray:
    """-> pixel_values [1, 3, size, size] as OWLv2 prepares an image: the 0..1 image padded to
    a square of its longest side with grey 0.5 at the bottom and right (the original OWLv2's
    and transformers 4.x's Owlv2ImageProcessor; transformers 5 pads with 0), resized as
    Owlv2ImageProcessor does (scipy: a Gaussian anti-alias when shrinking, then linear
    interpolation at half-pixel centres, mirrored at the edges, in float, no rounding to 8
    bits), clipped to the padded image's range, normalised.

    Each axis's resize is a fixed matrix with a few taps a row (cached per size), applied by
    gathers; equal to `owl_inputs_reference` within 5e-6 and to the processor within 1e-5
    (tests/models/test_res_processing.py)."""
    pad = _owl_padded(rgb)
    side = pad.shape[0]
    idx, wt = _owl_taps(side, size)
    y = np.einsum("othc,ot->ohc", pad[idx], wt)  # [size, side, 3]
    y = np.einsum("optc,pt->opc", y[:, idx], wt)  # [size, size, 3]
    return _owl_finished(y, pad, mean, std)


def owl_logits(
    class_embeds: np.ndarray, shift: np.ndarray, scale: np.ndarray, query: np.ndarray
) -> np.ndarray:
    """OWLv2's class head after its embeddings: class_embeds [P, D] (normalised), shift [P],
    scale [P] (elu + 1 applied), the query [D] (normalised) -> logits [P]."""
    # einsum's own loop, not BLAS: OpenBLAS's threads spin for a while after a call and slowed
    # the SAM decoder run that follows on the same 2 cores from 0.08 to 0.14 s
    dots = np.einsum("pd,d->p", class_embeds.astype(np.float32), query.astype(np.float32))
    out: np.ndarray = (dots + shift.astype(np.float32)) * scale.astype(np.float32)
    return out


def owl_detections(
    logits: np.ndarray,
    boxes: np.ndarray,
    image_hw: tuple[int, int],
    box_threshold: float,
    max_boxes: int,
) -> tuple[np.ndarray, np.ndarray]:
    """One query's logits [P] and boxes [P, 4] (cx, cy, w, h relative to the padded square) ->
    boxes [K, 4] (x0, y0, x1, y1 in pixels of the image) and scores [K], best first:
    Owlv2ImageProcessor.post_process_object_detection (sigmoid, threshold, boxes scaled by the
    longest side), then the best `max_boxes`."""
    scores = sigmoid(logits.astype(np.float32))
    cx, cy, bw, bh = (boxes[:, i].astype(np.float32) for i in range(4))
    xyxy = np.stack([cx - 0.5 * bw, cy - 0.5 * bh, cx + 0.5 * bw, cy + 0.5 * bh], -1)
    side = np.float32(max(image_hw))
    xyxy = xyxy * side
    keep = np.flatnonzero(scores > box_threshold)
    keep = keep[np.argsort(-scores[keep], kind="stable")][:max_boxes]
    return xyxy[keep].astype(np.float32), scores[keep].astype(np.float32)
