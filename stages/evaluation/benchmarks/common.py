"""What every benchmark reader returns, and the image reading the reference scripts share.

A reader turns a downloaded benchmark scene into queries (a prompt text and the id its RES masks
are filed under) and frames (an annotated image matched to the scene's camera as the reference
code matches it, with its ground truth per query). Readers check everything before any work:
what the reference code would crash on is a GoiError naming the file and field; what it would
skip is skipped with a named warning.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages.core.errors import GoiError, warn
from stages.query.prompts import check_plain_name, safe_name
from stages.scene.cameras import Camera


@dataclass
class Query:
    id: str  # a plain name: RES masks are filed under <res>/<id>/<view>.png; the report's key
    text: str  # the prompt (its text embedding's key)


@dataclass
class Frame:
    key: str  # the annotation's name of the frame (frame_00001, 03, DSCF4667, rgb_12)
    camera: Camera  # the matched camera, scaled to the ground truth's size
    source: Path  # the annotation file or folder, for messages
    gts: dict[str, np.ndarray]  # query id -> [H, W] ground truth (bool, or uint8 grey)
    boxes: dict[str, np.ndarray] = field(default_factory=dict)  # query id -> [K, 4] x1 y1 x2 y2


@dataclass
class BenchmarkScene:
    name: str
    dir: Path  # the benchmark's directory of this scene (annotations)
    queries: list[Query]
    frames: list[Frame]
    held_out: set[str] = field(default_factory=set)  # camera names the field must not train on
    skipped: list[str] = field(default_factory=list)  # what was skipped, as the reference does
    layout: str = ""  # which of a benchmark's accepted layouts was found (LERF-Mask's folders)


#: the longest query text that is its own id (a file name has at most 255 bytes)
MAX_ID_BYTES = 200


def query_id(text: str) -> str:
    """The id a query's RES masks are filed under: the text itself when it is a plain name
    (e.g. 'green apple') short enough to be a file name, else its safe_name. A query's text is
    data: it reaches the file system only as this id."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_ID_BYTES:
        return safe_name(text)
    try:
        return check_plain_name(text, "query")
    except GoiError:
        return safe_name(text)


def skip(scene: BenchmarkScene, message: str) -> None:
    """A frame or query the reference code would skip: a named warning, and recorded."""
    scene.skipped.append(message)
    warn(message)


def camera_or_skip(
    scene: BenchmarkScene, cameras: dict[str, Camera], name: str, path: Path
) -> Camera | None:
    """The camera named `name` of the ground truth at `path`, or None, skipped with a warning:
    GOI's eval_seg.py skips a ground truth whose rendering is missing."""
    cam = cameras.get(name)
    if cam is None:
        skip(scene, f"{path}: no camera named {name!r}; skipped, as eval_seg.py skips it")
    return cam


def frame_index(
    text: str,
    parse: Callable[[str], int],
    n: int,
    unparsed: str,
    outside: tuple[str, str],
    first: int = 0,
) -> int:
    """A frame's index into its scene's `n` cameras or images from its number `parse(text)`,
    counted from `first`: a text it cannot parse is refused with `unparsed`, a number outside
    the n with `outside` = (the words before, the words after) the number."""
    try:
        number = parse(text)
    except ValueError:
        raise GoiError(unparsed) from None
    if not first <= number < first + n:
        raise GoiError(f"{outside[0]}{number}{outside[1]}")
    return number - first


#: A ground truth may be at most this many times its camera's size on a side (Mip-NeRF360's
#: full-size masks against cameras trained on images_8); checked before any array is made.
MAX_SCALE = 8


def scaled_to(cam: Camera, width: int, height: int, where: str) -> Camera:
    """The camera rendered at the ground truth's size; the aspect ratios must agree (1%) and
    the size be at most MAX_SCALE times the camera's on a side."""
    if width < 2 or height < 2:
        raise GoiError(f"{where}: ground truth of {width}x{height} pixels")
    if width > MAX_SCALE * cam.width or height > MAX_SCALE * cam.height:
        raise GoiError(
            f"{where}: ground truth of {width}x{height} pixels, more than {MAX_SCALE} times "
            f"its camera {cam.name!r} ({cam.width}x{cam.height}) on a side: not this scene's "
            "frame?"
        )
    if abs(width / height - cam.width / cam.height) > 0.01 * cam.width / cam.height:
        raise GoiError(
            f"{where}: ground truth is {width}x{height}, but its camera {cam.name!r} is "
            f"{cam.width}x{cam.height} (another aspect ratio: not this scene's frame?)"
        )
    if (width, height) == (cam.width, cam.height):
        return cam
    out = cam.scaled(width, height)
    out.name = f"{cam.name}_{width}x{height}"  # beside the training camera of the same image
    return out


def read_grey(path: Path, what: str) -> np.ndarray:
    """[H, W] uint8 as PIL's `Image.open(p).convert('L')` gives it (ITU-R 601-2 luma with
    PIL's integer rounding), which LERF-Mask's and 3D-OVS's scripts read masks with."""
    from stages.scene.images import _imread

    img = _imread(path, what)
    if img.dtype != np.uint8:  # the benchmarks ship 8-bit PNGs; PIL's 'L' of others differs
        raise GoiError(f"{path}: {what} of type {img.dtype}; expected an 8-bit image")
    if img.ndim == 2:
        return img
    bgr = img[:, :, :3].astype(np.uint32)  # PIL's RGBA -> L ignores alpha too
    luma = (bgr[:, :, 2] * 19595 + bgr[:, :, 1] * 38470 + bgr[:, :, 0] * 7471 + 0x8000) >> 16
    return luma.astype(np.uint8)


def checked_size(cam: Camera, path: Path, what: str, same_as: Camera | None = None) -> Camera:
    """The camera at the size of the image `path`, read from its PNG or JPEG header and checked
    against the camera (scaled_to) before any pixel is decoded; with `same_as`, the size must
    be that camera's (the other masks of the frame)."""
    from stages.core.files import regular_file
    from stages.scene.images import image_size

    regular_file(path, what)
    try:
        size = image_size(path)
    except OSError as e:
        raise GoiError(f"{path}: cannot read the {what} ({e.strerror or e})") from None
    if size is None:
        raise GoiError(
            f"{path}: the {what} is not a PNG or JPEG (goi reads a ground truth's size from "
            "its header, before decoding it)"
        )
    w, h = size
    if same_as is not None:
        if (w, h) != (same_as.width, same_as.height):
            raise GoiError(
                f"{path}: {w}x{h}, but the frame's other masks are {same_as.width}x{same_as.height}"
            )
        return same_as
    return scaled_to(cam, w, h, str(path))


def read_grey_cv2(path: Path, what: str) -> np.ndarray:
    """[H, W] uint8 as `cv2.imread(p, cv2.IMREAD_GRAYSCALE)` gives it (GOI's eval_seg.py)."""
    import cv2

    from stages.scene.images import _imread

    return np.asarray(_imread(path, f"the {what}", cv2.IMREAD_GRAYSCALE))


def pil_nearest(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """`Image.fromarray(img).resize((width, height), Image.NEAREST)` in numpy: PIL samples the
    source pixel under each target pixel's centre (cv2's INTER_NEAREST takes the corner's)."""
    h, w = img.shape[:2]
    ys = np.minimum(((np.arange(height) + 0.5) * (h / height)).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * (w / width)).astype(np.int64), w - 1)
    return img[ys[:, None], xs[None, :]]


def image_name(cam: Camera) -> str:
    """A camera's image name as the 3DGS loaders the references build on take it:
    `os.path.basename(image_path).split(".")[0]`."""
    return Path(cam.image or cam.name).name.split(".")[0]


def sorted_by_image(cameras: list[Camera]) -> list[Camera]:
    """The cameras in the 3DGS loaders' order, which LangSplat and Gaussian Grouping index:
    `sorted(cam_infos_unsorted, key=lambda x: x.image_name)`."""
    return sorted(cameras, key=image_name)


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise GoiError(f"{path}: missing; {what}")
    return path
