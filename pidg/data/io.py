"""Shared reading helpers: strict JSON access and the parallel image loader all readers use.

A reader describes each frame it wants as a :class:`FrameSpec` (image file, time, how to build its camera,
optional mask file); :func:`load_frames` decodes the images on a thread pool (PIL releases the GIL while
decoding and resampling, numpy during array arithmetic, so threads overlap without the start-up and copying cost
of processes), composites RGBA on the background and resizes (in that order, or the other way round by D-NeRF's
protocol: ``DataConfig.resample``), and returns :class:`~pidg.data.scene.Frame` objects.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from tqdm.auto import tqdm

from pidg.data.scene import DataConfig, DatasetError, Frame, Resample
from pidg.render.camera import Camera

logger = logging.getLogger(__name__)

# Lanczos for images (sharp, little aliasing when shrinking; the Dry Ice frames were made with it too);
# nearest for masks, which must stay binary.
_IMAGE_FILTER = Image.Resampling.LANCZOS
_MASK_FILTER = Image.Resampling.NEAREST


# ---------------------------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------------------------
def read_json(path: Path) -> Any:
    """Parse a JSON file; a missing or malformed file raises DatasetError with json's line and column."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DatasetError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read file: {e}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DatasetError(path, f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None


def require(mapping: Any, key: str, path: Path, where: str = "") -> Any:
    """``mapping[key]``, or a DatasetError naming the file, the place (e.g. "frame 3") and the key."""
    prefix = f"{where}: " if where else ""
    if not isinstance(mapping, Mapping):
        raise DatasetError(path, f"{prefix}expected a JSON object, got {type(mapping).__name__}")
    if key not in mapping:
        raise DatasetError(path, f"{prefix}missing key '{key}'")
    return mapping[key]


def as_float(value: Any, path: Path, what: str) -> float:
    """A finite number from JSON (bools and strings rejected)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(path, f"{what} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise DatasetError(path, f"{what} is {value} (NaN or infinite)")
    return float(value)


def as_matrix(value: Any, rows: int, cols: int, path: Path, what: str) -> torch.Tensor:
    """A rows x cols float64 tensor from a nested JSON list (NaNs are left for the caller's checks)."""
    try:
        m = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise DatasetError(path, f"{what} must be a {rows}x{cols} list of numbers, got {value!r:.80}") from None
    if tuple(m.shape) != (rows, cols):
        raise DatasetError(path, f"{what} must be {rows}x{cols}, got shape {tuple(m.shape)}")
    return m


def as_vector(value: Any, n: int, path: Path, what: str) -> torch.Tensor:
    """A length-n finite float64 vector from a JSON list."""
    if not isinstance(value, list) or len(value) != n:
        raise DatasetError(path, f"{what} must be a list of {n} numbers, got {value!r:.80}")
    return torch.tensor([as_float(v, path, what) for v in value], dtype=torch.float64)


def check_time(value: float, path: Path, what: str) -> float:
    if not 0.0 <= value <= 1.0:
        raise DatasetError(path, f"{what}: time {value} is outside [0, 1]")
    return value


def select_subset(n: int, max_frames: int | None) -> list[int]:
    """Indices of at most ``max_frames`` evenly spaced items of ``n`` (first and last included)."""
    if max_frames is None or max_frames >= n:
        return list(range(n))
    if max_frames == 1:
        return [0]
    return sorted({round(i * (n - 1) / (max_frames - 1)) for i in range(max_frames)})


def fit_camera_to_image(camera: Camera, width: int, height: int, path: Path) -> Camera:
    """The camera for an image file of ``width`` x ``height``.

    Metadata may describe the original capture while the files were downscaled afterwards (e.g. intrinsics for a
    1920x1080 original beside 960x540 frames); that is accepted when the aspect ratio agrees, and the intrinsics
    are scaled. A different aspect ratio (the height it predicts is a pixel or more off; rounding a downscaled size
    stays below that) means the camera does not belong to the image.
    """
    if (camera.width, camera.height) == (width, height):
        return camera
    if abs(camera.height * width / camera.width - height) >= 1.0:
        raise DatasetError(
            path,
            f"image is {width}x{height} but its camera describes {camera.width}x{camera.height} (another aspect ratio)",
        )
    return camera.resized(width, height)


# ---------------------------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameSpec:
    """A frame to load. ``make_camera(width, height)`` builds its camera for the image size found on disk
    (so fov-only metadata gives the right intrinsics whatever the files' resolution)."""

    name: str
    image_path: Path
    time: float
    make_camera: Callable[[int, int], Camera]
    mask_path: Path | None = None
    depth_path: Path | None = None


def _open_image(path: Path, kind: str = "image") -> Image.Image:
    try:
        image = Image.open(path)
        image.load()
    except FileNotFoundError:
        raise DatasetError(path, f"{kind} file not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise DatasetError(path, f"cannot read {kind}: {e}") from None
    return image


# Modes whose pixels have no defined 0..255 range (float or 32-bit integer samples: radiance, counts, labels);
# converting them to 8 bits would clip or rescale by guesswork, so they are rejected.
_UNSCALED_MODES = {"F": "32-bit float", "I": "32-bit integer"}
_ALPHA_MODES = ("RGBA", "LA", "PA", "La", "RGBa")


def decode_rgb(path: Path, background: tuple[float, float, float], size: tuple[int, int] | None = None) -> np.ndarray:
    """[H, W, 3] float32 in [0, 255]; an alpha channel is composited: rgb * a + background * (1 - a).

    ``size`` (width, height): shrink the image there by the D-NeRF protocol (``DataConfig.resample`` area-rgba): the
    area average of the straight RGBA, then compositing (a 16-bit gray image, whose transparency is a colour key, is
    composited first). Kept in the 0..255 scale (not 0..1) to save a pass over the pixels; the in-place arithmetic
    (rgb - bg) * a + bg is about 5x faster than the broadcast expression on an 800x800 frame.
    16-bit PNGs: PIL already hands RGB(A) and gray+alpha over with 8-bit samples (the high byte of each), but plain
    16-bit gray as mode I;16 ("I" in older Pillow), which is scaled here: PIL's own conversion would clip it at 255.
    """
    return _decode_opened(_open_image(path), path, background, size)


def _decode_opened(image: Image.Image, path: Path, background: tuple[float, float, float], size: tuple[int, int] | None) -> np.ndarray:
    """:func:`decode_rgb` of an opened image."""
    if image.mode.startswith("I;16") or (image.mode == "I" and image.format == "PNG"):  # PNG has no 32-bit gray
        rgb = _decode_gray16(image, path, background)
        return rgb if size is None else _area_resize(rgb, size)
    if image.mode in _UNSCALED_MODES:
        raise DatasetError(
            path,
            f"image mode {image.mode!r} ({_UNSCALED_MODES[image.mode]} samples) has no 0..255 range; "
            f"frames must be 8- or 16-bit pictures (e.g. PNG)",
        )
    has_alpha = image.mode in _ALPHA_MODES or "transparency" in image.info  # P, L or RGB with a tRNS chunk
    if image.mode != ("RGBA" if has_alpha else "RGB"):
        try:
            image = image.convert("RGBA" if has_alpha else "RGB")
        except ValueError as e:
            raise DatasetError(path, f"cannot convert image mode {image.mode!r} to RGB: {e}") from None
    array = np.asarray(image)
    if has_alpha and image.getchannel("A").getbbox() is None:  # C-speed scan, stops at the first nonzero alpha
        raise DatasetError(path, "alpha is zero everywhere: the frame is pure background, nothing to learn from")
    if size is not None:
        small = _area_resize(array.astype(np.float32), size)
        return _composite_straight(small[..., :3], small[..., 3:4] * (1.0 / 255.0), background) if has_alpha else small
    if has_alpha:
        return composite_rgba_float(array, background)
    return array[..., :3].astype(np.float32)


def _area_resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """OpenCV's area average (INTER_AREA: each output pixel the mean of the input area it covers) of a float32
    [H, W, 3 or 4] image to (width, height)."""
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _decode_gray16(image: Image.Image, path: Path, background: tuple[float, float, float]) -> np.ndarray:
    """A 16-bit gray image as [H, W, 3] float32 in [0, 255] (v * 255 / 65535, the rounding left to the caller);
    a tRNS transparent gray level becomes background."""
    gray = np.asarray(image)
    level = gray.astype(np.float32)
    level *= 255.0 / 65535.0  # scaled once, before the copy to three channels
    rgb = np.repeat(level[..., None], 3, axis=2)
    key = image.info.get("transparency")
    if isinstance(key, int):
        clear = gray == key
        if clear.all():
            raise DatasetError(path, "alpha is zero everywhere: the frame is pure background, nothing to learn from")
        rgb[clear] = np.asarray(background, np.float32) * 255.0
    return rgb


def composite_rgba_float(rgba: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """RGBA uint8 [H, W, 4] -> RGB float32 in [0, 255] on ``background``: (rgb - bg) * a + bg, in place."""
    alpha = rgba[..., 3:4].astype(np.float32)
    alpha *= 1.0 / 255.0
    return _composite_straight(rgba[..., :3].astype(np.float32), alpha, background)


def _composite_straight(rgb: np.ndarray, alpha: np.ndarray, background: tuple[float, float, float]) -> np.ndarray:
    """Straight colour [H, W, 3] float32 in [0, 255] with alpha [H, W, 1] in [0, 1] on ``background``, in ``rgb``."""
    bg = np.asarray(background, np.float32) * 255.0
    rgb -= bg
    rgb *= alpha
    rgb += bg
    return rgb


def decode_mask(path: Path) -> np.ndarray:
    """[H, W] bool: True where any colour channel is nonzero (the alpha of an RGBA mask is ignored)."""
    array = np.asarray(_open_image(path, "mask"))
    if array.ndim == 3:
        array = array[..., :3].max(axis=2) if array.shape[2] >= 3 else array[..., 0]
    return array > 0


def decode_depth(path: Path) -> np.ndarray:
    """[H, W] float32 camera-z depth in scene units from a ``.npy`` or ``.npz`` file; 0 = unknown (non-finite
    values too: renderers write +inf or NaN where a ray hits nothing)."""
    depth = _load_depth_array(path)
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    real = np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)
    if depth.ndim != 2 or not real:
        raise DatasetError(path, f"depth map must be a 2D real array [H, W], got {depth.dtype} {list(depth.shape)}")
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    if (depth < 0).any():
        raise DatasetError(path, "depth map has negative values (expected camera z >= 0, 0 = unknown)")
    return depth


_NPY_MAGIC, _NPZ_MAGICS = b"\x93NUMPY", (b"PK\x03\x04", b"PK\x05\x06")  # as np.load tells them apart


def _load_depth_array(path: Path) -> np.ndarray:
    """The array of a ``.npy`` file, or of a ``.npz`` the one named "depth" or its only array.

    An ``.npz`` with several arrays and none named "depth" is rejected rather than read by position: its first
    array may as well be a disparity or a confidence map.
    """
    try:
        with open(path, "rb") as file:
            magic = file.read(len(_NPY_MAGIC))
            if not magic.startswith((_NPY_MAGIC, *_NPZ_MAGICS)):  # numpy would try to unpickle it and say so
                raise DatasetError(path, "cannot read depth map: not a NumPy .npy or .npz file")
            file.seek(0)
            loaded = np.load(file, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                return loaded
            with loaded:
                names = list(loaded.files)
                if "depth" not in names and len(names) != 1:
                    raise DatasetError(
                        path, f"depth .npz holds arrays {names}; expected one array or one named 'depth'"
                    )
                return loaded["depth" if "depth" in names else names[0]]
    except DatasetError:
        raise
    except FileNotFoundError:
        raise DatasetError(path, "depth file not found") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:  # truncated, corrupt, object arrays
        raise DatasetError(path, f"cannot read depth map: {e}") from None


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize: averaging depths across an object boundary would invent surfaces."""
    return np.array(Image.fromarray(depth).resize((width, height), Image.Resampling.NEAREST))  # a writable copy


def resize_rgb(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a float image per channel (PIL mode "F", so no 8-bit rounding before the filter)."""
    channels = [
        np.asarray(Image.fromarray(np.ascontiguousarray(rgb[..., c])).resize((width, height), _IMAGE_FILTER))
        for c in range(rgb.shape[2])
    ]
    return np.stack(channels, axis=2)


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    return np.asarray(Image.fromarray(mask.astype(np.uint8) * 255).resize((width, height), _MASK_FILTER)) > 0


def _aligned_map(path: Path | None, decode: Callable[[Path], np.ndarray], what: str, width: int, height: int) -> np.ndarray | None:
    """A per-pixel map belonging to an image (mask, depth), checked to have the image's size; None without a file."""
    if path is None:
        return None
    values = decode(path)
    if values.shape != (height, width):
        raise DatasetError(path, f"{what} is {values.shape[1]}x{values.shape[0]} but its image is {width}x{height}")
    return values


def _load_one(spec: FrameSpec, config: DataConfig, resample: Resample) -> tuple[Frame, tuple[int, int]]:
    image = _open_image(spec.image_path)
    width, height = image.size
    tw, th = config.target_size(width, height)
    shrink = (tw, th) != (width, height)
    area = shrink and resample == "area-rgba"  # shrunk while decoding: the area average comes before compositing
    rgb = _decode_opened(image, spec.image_path, config.background_rgb, (tw, th) if area else None)
    camera = spec.make_camera(width, height)
    mask = _aligned_map(spec.mask_path, decode_mask, "mask", width, height)
    depth = _aligned_map(spec.depth_path, decode_depth, "depth map", width, height)
    if shrink:
        if not area:
            rgb = resize_rgb(rgb, tw, th)
        camera = camera.resized(tw, th)
        mask = resize_mask(mask, tw, th) if mask is not None else None
        depth = resize_depth(depth, tw, th) if depth is not None else None
    np.clip(np.rint(rgb, out=rgb), 0, 255, out=rgb)  # the Lanczos filter can overshoot
    image_u8 = torch.from_numpy(rgb.astype(np.uint8))
    mask_t = None if mask is None else torch.from_numpy(mask)
    depth_t = None if depth is None else torch.from_numpy(depth)
    return Frame(camera, spec.time, image_u8, mask_t, spec.name, spec.image_path, depth_t), (width, height)


def load_frames(specs: Sequence[FrameSpec], config: DataConfig, desc: str, *, resample: Resample) -> list[Frame]:
    """Decode all frames of one split (in parallel, with a progress bar) and check they share one size; ``resample``:
    ``DataConfig.resample`` as the dataset's loader resolved it (not auto)."""
    if resample == "auto":
        raise ValueError("load_frames: resolve DataConfig.resample 'auto' for the dataset first")
    workers = config.num_workers or min(8, os.cpu_count() or 1)
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = list(
            tqdm(
                pool.map(lambda s: _load_one(s, config, resample), specs),
                total=len(specs),
                desc=desc,
                unit="img",
                disable=None if config.progress else True,
                leave=False,
            )
        )
    if results:
        first_size, first_path = results[0][1], specs[0].image_path
        for (_, size), spec in zip(results, specs):
            if size != first_size:
                raise DatasetError(
                    spec.image_path,
                    f"image is {size[0]}x{size[1]} but the split's first frame ({first_path}) is "
                    f"{first_size[0]}x{first_size[1]}; frames of a split must share one size",
                )
        frame = results[0][0]
        logger.info(
            "%s: %d frames of %dx%d (files %dx%d%s) in %.1f s",
            desc,
            len(results),
            frame.width,
            frame.height,
            first_size[0],
            first_size[1],
            f", shrunk by {resample}" if (frame.width, frame.height) != first_size else "",
            time.perf_counter() - start,
        )
    return [frame for frame, _ in results]


def camera_or_error(build: Callable[[], Camera], path: Path, where: str) -> Camera:
    """Run a Camera constructor, turning its ValueError (not rigid, NaN, bad intrinsics) into a DatasetError."""
    try:
        return build()
    except ValueError as e:
        raise DatasetError(path, f"{where}: {e}") from None
