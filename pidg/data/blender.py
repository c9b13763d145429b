"""Reader for Blender-style dynamic datasets: D-NeRF, BlenderNeRF exports and the PIDG physics scenes.

Layout::

    transforms_{train,val,test}.json   any subset; each: camera_angle_x [, camera_angle_y]
                                       or fl_x [, fl_y, cx, cy, w, h]; frames: file_path, time, transform_matrix
    <file_path>[.png]                  RGBA or RGB frames; file_path may omit the extension
    mask/<frame file name>.png         optional motion masks (nonzero = dynamic), PIDG scenes
    depth/<frame file name>.npy|.npz   optional depth maps: float32 [H, W] camera z in scene units, 0 (or NaN,
                                       inf) = unknown; an .npz holds one array or one named "depth"
                                       (used by the flow decomposition instead of the model's rendered depth)
    points3d.ply                       optional initial point cloud, PIDG scenes

``transform_matrix`` is an OpenGL/Blender camera-to-world matrix; ``Camera.from_fov`` converts it. Intrinsic keys
may sit at the top level or in a frame (per-frame values win, as in nerfstudio's format). ``fl_x``/``cx``... are
pixels of a ``w`` x ``h`` image; when the files have another size of the same aspect the camera is scaled.

Time: ``DataConfig.time_source = "json"`` takes each frame's ``time``; ``"frame_number"`` uses the number ending
the file name, t = (k - kmin) / (kmax - kmin) over the frames of *all* split files, which is the true time for
data such as Dry Ice whose json times were normalised per split (see the data README). In json mode, when frame
numbers do identify frames and the json times disagree with them, a warning says so.
"""

from __future__ import annotations

import logging
import math
import posixpath
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import torch

from pidg.data.io import (
    FrameSpec,
    as_float,
    as_matrix,
    camera_or_error,
    check_time,
    fit_camera_to_image,
    load_frames,
    read_json,
    require,
    select_subset,
)
from pidg.data.ply import read_ply_points
from pidg.data.scene import SPLIT_NAMES, DataConfig, DatasetError, SceneData, compute_bounds
from pidg.render.camera import Camera

logger = logging.getLogger(__name__)

_INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
_FRAME_NUMBER = re.compile(r"(\d+)$")
_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def transforms_path(root: Path, split: str) -> Path:
    return root / f"transforms_{split}.json"


def is_blender_dataset(root: Path) -> bool:
    return any(transforms_path(root, s).is_file() for s in SPLIT_NAMES)


def blender_layout(root: Path) -> str:
    """"pidg" for PIDG / BlenderNeRF physics scenes (motion masks or an initial point cloud), else "dnerf"."""
    return "pidg" if ((root / "mask").is_dir() or (root / "points3d.ply").is_file()) else "dnerf"


@dataclass(frozen=True)
class _Intrinsics:
    """Intrinsics as the json gives them: a field of view, or focal lengths/principal point in pixels of w x h."""

    camera_angle_x: float | None = None
    camera_angle_y: float | None = None
    fl_x: float | None = None
    fl_y: float | None = None
    cx: float | None = None
    cy: float | None = None
    w: int | None = None
    h: int | None = None

    def camera(self, c2w_gl: torch.Tensor, width: int, height: int) -> Camera:
        """The camera for an image of ``width`` x ``height`` pixels as found on disk."""
        # Size the intrinsics refer to: the json's w x h when given, else the image itself.
        w0, h0 = (self.w, self.h) if self.w is not None and self.h is not None else (width, height)
        if self.fl_x is not None:
            fl_y = self.fl_y if self.fl_y is not None else self.fl_x
            cam = Camera.from_fov(c2w_gl, w0, h0, 2 * math.atan(0.5 * w0 / self.fl_x), 2 * math.atan(0.5 * h0 / fl_y))
            if self.cx is not None or self.cy is not None:
                # Off-centre principal point: pixels from the top-left corner, the same in nerfstudio's
                # format and in Camera (OpenCV); only the value differs from from_fov's centred default.
                cx = self.cx if self.cx is not None else cam.cx
                cy = self.cy if self.cy is not None else cam.cy
                cam = replace(cam, cx=cx, cy=cy)
        else:
            assert self.camera_angle_x is not None
            cam = Camera.from_fov(c2w_gl, w0, h0, self.camera_angle_x, self.camera_angle_y)
        return cam


@dataclass(frozen=True)
class _JsonFrame:
    json_path: Path
    index: int  # position in the json's frame list, for error messages
    file_path: str
    time: float | None  # validated json time, None when absent or not used
    c2w: torch.Tensor  # [4, 4] float64, OpenGL camera-to-world
    intrinsics: _Intrinsics

    @property
    def where(self) -> str:
        return f"frame {self.index} ({self.file_path!r})"

    @property
    def key(self) -> str:
        """The frame's file, normalised so that 'train/0002' and './train/0002.png' compare equal."""
        path = posixpath.normpath(self.file_path.replace("\\", "/"))
        stem, ext = posixpath.splitext(path)
        return stem if ext.lower() in _IMAGE_EXTENSIONS else path

    @property
    def image_id(self) -> str:
        """Which image file the entry names, as :func:`_image_path` finds it: 'train/0002' and './train/0002.png'
        are one file, 'a.png' and 'a.jpg' two (``key`` strips both extensions)."""
        path = posixpath.normpath(self.file_path.replace("\\", "/"))
        return path[: -len(".png")] if path.endswith(".png") else path

    @property
    def file_name(self) -> str:
        """File name without directory and image extension ('train/0002.png' -> '0002')."""
        return posixpath.basename(self.key)

    @property
    def number(self) -> int | None:
        m = _FRAME_NUMBER.search(self.file_name)
        return int(m.group(1)) if m else None


def _read_intrinsics(source: dict, fallback: _Intrinsics | None, path: Path, where: str) -> _Intrinsics:
    values: dict[str, float | int | None] = {} if fallback is None else dict(fallback.__dict__)
    for key in _INTRINSIC_KEYS:
        if key in source:
            number = as_float(source[key], path, f"{where}'{key}'")
            if number <= 0 and key not in ("cx", "cy"):
                raise DatasetError(path, f"{where}'{key}' must be positive, got {number}")
            values[key] = int(number) if key in ("w", "h") else number
    intr = _Intrinsics(**values)  # type: ignore[arg-type]
    if fallback is not None and intr.camera_angle_x is None and intr.fl_x is None:
        raise DatasetError(path, f"{where}no intrinsics: need 'camera_angle_x' or 'fl_x'")
    if (intr.w is None) != (intr.h is None):
        raise DatasetError(path, f"{where}give both 'w' and 'h' or neither")
    return intr


def _read_split(path: Path, use_json_time: bool) -> list[_JsonFrame]:
    meta = read_json(path)
    top = _read_intrinsics(meta if isinstance(meta, dict) else {}, None, path, "")
    frames = require(meta, "frames", path)
    if not isinstance(frames, list) or not frames:
        raise DatasetError(path, "'frames' must be a non-empty list")
    out = []
    for i, frame in enumerate(frames):
        where = f"frame {i}"
        file_path = require(frame, "file_path", path, where)
        if not isinstance(file_path, str) or not file_path:
            raise DatasetError(path, f"{where}: 'file_path' must be a non-empty string")
        where = f"frame {i} ({file_path!r})"
        intr = _read_intrinsics(frame, top, path, f"{where}: ")
        c2w = as_matrix(require(frame, "transform_matrix", path, where), 4, 4, path, f"{where}: 'transform_matrix'")
        # Run Camera's own checks (rigid, finite, positive focal) on every frame now, before decoding images; the
        # size is nominal, the real camera is built for the decoded image.
        camera_or_error(partial(intr.camera, c2w, intr.w or 64, intr.h or 64), path, f"{where}: 'transform_matrix'")
        time = None
        if "time" in frame and use_json_time:
            time = check_time(as_float(frame["time"], path, f"{where}: 'time'"), path, where)
        out.append(_JsonFrame(path, i, file_path, time, c2w, intr))
    return out


def _frame_number_times(frames: dict[str, list[_JsonFrame]]) -> dict[str, list[float]]:
    """t = (k - kmin) / (kmax - kmin) with k the number ending each file name, over every split."""
    files_of: dict[int, str] = {}
    for split_frames in frames.values():
        for f in split_frames:
            k = f.number
            if k is None:
                raise DatasetError(
                    f.json_path, f"{f.where}: no frame number at the end of the file name (time_source='frame_number')"
                )
            if files_of.setdefault(k, f.key) != f.key:
                raise DatasetError(
                    f.json_path,
                    f"{f.where}: frame number {k} also names '{files_of[k]}'; frame numbers do not identify video "
                    f"frames in this dataset, use time_source='json'",
                )
    kmin, kmax = min(files_of), max(files_of)
    if kmax == kmin:
        path = next(iter(frames.values()))[0].json_path
        raise DatasetError(path, f"all frames have number {kmin}; cannot derive time")
    return {s: [(f.number - kmin) / (kmax - kmin) for f in fs] for s, fs in frames.items()}  # type: ignore[operator]


def _json_vs_frame_number(frames: dict[str, list[_JsonFrame]]) -> tuple[float, int] | None:
    """(largest |json time - frame-number time|, kmax - kmin) when frame numbers identify frames, else None."""
    try:
        by_number = _frame_number_times(frames)
    except DatasetError:
        return None
    diffs = [abs(f.time - t) for s, fs in frames.items() for f, t in zip(fs, by_number[s]) if f.time is not None]
    numbers = [f.number for fs in frames.values() for f in fs]
    return (max(diffs), max(numbers) - min(numbers)) if diffs else None  # type: ignore[type-var, operator]


def _assign_times(frames: dict[str, list[_JsonFrame]], config: DataConfig) -> tuple[dict[str, list[float]], str]:
    if config.time_source == "frame_number":
        return _frame_number_times(frames), "frame_number"
    times: dict[str, list[float]] = {}
    used_index = False
    for split, fs in frames.items():
        missing = [f for f in fs if f.time is None]
        if not missing:
            times[split] = [f.time for f in fs]  # type: ignore[misc]
        elif config.allow_missing_time and len(missing) == len(fs):
            times[split] = [i / (len(fs) - 1) if len(fs) > 1 else 0.0 for i in range(len(fs))]
            used_index = True
        else:
            f = missing[0]
            hint = "" if config.allow_missing_time else " (set allow_missing_time to use index / (n - 1))"
            raise DatasetError(f.json_path, f"{f.where}: missing key 'time'; this is a dynamic dataset{hint}")
    return times, "index" if used_index else "json"


# Two entries of one file agree when times and matrix entries differ by at most this (for translations, times
# their size): far above the rounding of printed floats, far below anything meaningful (a frame of a
# 10,000-frame video, 0.006 degrees).
_SAME_ENTRY_TOLERANCE = 1e-4


def _check_repeated_images(
    frames: dict[str, list[_JsonFrame]], times: dict[str, list[float]], time_source: str
) -> None:
    """An image file listed twice (in one split file or two) must be one picture: the same time and camera pose.

    Identical repeats only get a warning: within a split they merely weight a frame twice, and across splits they
    are sometimes deliberate (exports that write val = test, a training view evaluated on purpose), so refusing to
    load would cost more than saying so; the warning says when a training image sits in an evaluation split, where
    it inflates the scores. Index times (time source "index") are list positions, not data: only poses count there.
    """
    first: dict[str, tuple[str, _JsonFrame, float]] = {}
    repeats: list[str] = []
    in_evaluation = 0
    for split, split_frames in frames.items():
        for f, t in zip(split_frames, times[split]):
            other_split, g, other_t = first.setdefault(f.image_id, (split, f, t))
            if g is f:
                continue
            other = g.where if g.json_path == f.json_path else f"{g.where} of {g.json_path.name}"
            pose_gap = float((f.c2w - g.c2w).abs().max())
            if time_source != "index" and abs(t - other_t) > _SAME_ENTRY_TOLERANCE:
                conflict = f"another time ({t:g} here, {other_t:g} there)"
            elif pose_gap > _SAME_ENTRY_TOLERANCE * max(1.0, float(g.c2w[:3, 3].abs().max())):
                conflict = f"another camera pose ('transform_matrix' entries differ by up to {pose_gap:.3g})"
            else:
                repeats.append(f"{f.json_path.name} {f.where} repeats {other}")
                in_evaluation += other_split == "train" and split != "train"
                continue
            raise DatasetError(f.json_path, f"{f.where} names the same image as {other} with {conflict}")
    if repeats:
        leak = ""
        if in_evaluation:
            leak = f"; {in_evaluation} are training images in an evaluation split (inflated scores)"
        logger.warning("%d image(s) listed twice with identical entries, e.g. %s%s", len(repeats), repeats[0], leak)


def _image_path(root: Path, f: _JsonFrame) -> Path:
    """The frame's file: file_path + '.png' first (BlenderNeRF/D-NeRF omit it), then file_path as written."""
    candidates = [root / (f.file_path + ".png"), root / f.file_path]
    for c in candidates:
        if c.is_file():
            return c
    raise DatasetError(
        candidates[0], f"image file not found ({f.where} of {f.json_path.name}; also tried {candidates[1]})"
    )


def _depth_path(depth_dir: Path, f: _JsonFrame) -> Path | None:
    """depth/<frame>.npy or depth/<frame>.npz; None when the frame has neither (the model's depth is used)."""
    found = [p for p in (depth_dir / f"{f.file_name}.npy", depth_dir / f"{f.file_name}.npz") if p.is_file()]
    if len(found) == 2:  # which one is meant is a guess
        raise DatasetError(found[1], f"{found[0].name} exists too; keep one depth map per frame")
    return found[0] if found else None


def read_blender(config: DataConfig) -> SceneData:
    """Read a D-NeRF / BlenderNeRF / PIDG folder (see the module docstring)."""
    root = config.root
    available = [s for s in SPLIT_NAMES if transforms_path(root, s).is_file()]
    if not available:
        raise DatasetError(root, "no transforms_{train,val,test}.json found")
    missing = [s for s in config.splits if s not in available]
    if missing:
        raise DatasetError(
            transforms_path(root, missing[0]),
            f"split '{missing[0]}' was requested but its file does not exist (available: {available})",
        )

    # Every split file is parsed (json only, cheap) even when not loaded: times from frame numbers and the scene
    # bounds must not depend on which splits or how many frames are loaded.
    use_json_time = config.time_source == "json"
    json_frames = {s: _read_split(transforms_path(root, s), use_json_time) for s in available}
    times, time_source = _assign_times(json_frames, config)
    _check_repeated_images(json_frames, times, time_source)
    logger.info("%s: frame times from %s", root.name, time_source)
    info: dict[str, object] = {}
    if time_source == "json":
        comparison = _json_vs_frame_number(json_frames)
        if comparison is not None:
            gap, span = comparison
            info["json_time_vs_frame_number"] = gap
            if gap * span > 0.5:  # more than half a frame interval: the json times are not the frames' times
                logger.warning(
                    "%s: json times differ from the frame numbers' times by up to %.4f (%.1f frames); "
                    "time_source='frame_number' gives each frame its own time",
                    root.name,
                    gap,
                    gap * span,
                )

    layout = blender_layout(root)
    resample = config.resample_for(layout)
    mask_dir = root / "mask"
    use_masks = config.load_masks and mask_dir.is_dir()
    depth_dir = root / "depth"
    has_depth_dir = depth_dir.is_dir()
    splits = {}
    for split in config.splits:
        chosen = select_subset(len(json_frames[split]), config.max_frames)
        specs = []
        for i in chosen:
            f, t = json_frames[split][i], times[split][i]
            image_path = _image_path(root, f)
            specs.append(
                FrameSpec(
                    name=f.key,
                    image_path=image_path,
                    time=t,
                    make_camera=_camera_builder(f, image_path),
                    mask_path=mask_dir / f"{f.file_name}.png" if use_masks else None,
                    depth_path=_depth_path(depth_dir, f) if has_depth_dir else None,
                )
            )
        splits[split] = load_frames(specs, config, desc=f"{root.name}/{split}", resample=resample)

    points = read_ply_points(root / "points3d.ply") if (root / "points3d.ply").is_file() else None
    # Bounds from all training cameras (all frames of every split if there is no training file).
    bound_frames = json_frames["train"] if "train" in json_frames else [f for fs in json_frames.values() for f in fs]
    centers = torch.stack([f.c2w[:3, 3] for f in bound_frames])
    info["layout"] = layout
    info["resample"] = resample
    info["masks"] = use_masks
    # True only when some loaded frame has a depth map: a depth/ folder whose names match no frame gives none.
    info["depth_maps"] = any(frame.depth is not None for frames in splits.values() for frame in frames)
    if has_depth_dir and not info["depth_maps"]:
        logger.warning(
            "%s: depth/ holds no <frame file name>.npy or .npz for the loaded frames; using rendered depth", depth_dir
        )
    return SceneData(
        root=root,
        kind="blender",
        splits=splits,
        background=torch.tensor(config.background_rgb, dtype=torch.float32),
        bounds=compute_bounds(centers, points),
        time_source=time_source,
        points3d=points,
        info=info,
    )


def _camera_builder(f: _JsonFrame, image_path: Path) -> Callable[[int, int], Camera]:
    def build(width: int, height: int) -> Camera:
        camera = camera_or_error(lambda: f.intrinsics.camera(f.c2w, width, height), f.json_path, f.where)
        return fit_camera_to_image(camera, width, height, image_path)

    return build
