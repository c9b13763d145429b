"""What every dataset reader produces: frames (camera, time, image, mask) per split plus scene-level data.

Readers (``blender.py``, ``hypernerf.py``) turn a dataset folder into a :class:`SceneData`; nothing downstream
knows which format the data came from. Images are decoded once at load time and kept in memory, so a training
step never touches the disk.

Images are stored as ``uint8`` [H, W, 3] (already composited on the background and resized) and converted to
``float32`` in [0, 1] on access (:attr:`Frame.image`). Why: 4x less memory than float32 (an 800x800 D-NeRF scene
with all three splits is 0.36 GB instead of 1.5 GB; a HyperNeRF scene with ~500 frames at 536x960 is 0.8 GB
instead of 3 GB), while the conversion costs about a millisecond, negligible next to a render step. The 8-bit
rounding of the composited colour (error <= 0.5/255) matches what the reference 3DGS-family pipelines do (they
composite, then store an 8-bit PIL image) and the PNGs that evaluation images are compared against.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import torch
from torch import Tensor

from pidg.config_tools import AT_LEAST_ONE, NON_NEGATIVE, POSITIVE, UNIT, validate_config
from pidg.render.camera import Camera

logger = logging.getLogger(__name__)

Background = Literal["white", "black"]
TimeSource = Literal["json", "frame_number"]
Resample = Literal["auto", "lanczos", "area-rgba"]
HyperNerfSplit = Literal["vrig", "interp"]

#: Splits a reader may return. HyperNeRF's ``val_ids`` (the held-out views) become ``"test"``.
SPLIT_NAMES = ("train", "val", "test")


class DatasetError(ValueError):
    """A dataset file is missing, unreadable or inconsistent. The message names the file and the problem."""

    def __init__(self, path: Path | str, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


# ---------------------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DataConfig:
    """How to read a dataset folder.

    ``downscale`` is either a factor (2 halves both sides; 1 keeps the files' size) or a target size
    ``(width, height)``, e.g. ``(400, 400)`` for the NeRF-era D-NeRF protocol. ``parse_downscale`` turns the
    strings ``"2"`` / ``"400x400"`` into these.

    ``time_source`` matters for Blender-style data only: ``"json"`` uses each frame's ``time``;
    ``"frame_number"`` derives it from the number at the end of the file name, normalised over all splits
    (needed for the Dry Ice scene, whose json times are normalised per split, see the data README).
    HyperNeRF times always come from ``metadata.json``.

    ``max_frames`` keeps an evenly spaced subset (first and last frame included) of each split, for tests and
    quick looks; time normalisation and scene bounds still use every frame listed in the files, so a subset has
    the same times and bounds as the full scene.
    """

    path: Path | str
    """The dataset folder (D-NeRF / BlenderNeRF / PIDG: transforms_*.json; HyperNeRF / Nerfies: dataset.json)."""
    background: Background = "black"
    """Background the RGBA images are composited on and the renders are drawn over (the PIDG paper: black)."""
    downscale: Annotated[float | tuple[int, int], POSITIVE] = 1.0
    """Image size: a factor (2 halves both sides) or WIDTHxHEIGHT, e.g. 400x400 for the NeRF-era D-NeRF protocol."""
    resample: Resample = "auto"
    """How images are shrunk to ``downscale``. lanczos: composited on the background at full size, then a Lanczos
    filter (sharp). area-rgba: the protocol of D-NeRF's and TiNeuVox's loaders, whose published 400x400 tables are
    scored against it: OpenCV's area average of the straight (not premultiplied) RGBA, then composited on the
    background. auto: area-rgba for D-NeRF scenes (so that their PSNR compares with those tables), lanczos for the
    others."""
    time_source: TimeSource = "json"
    """Blender-style data: json uses each frame's time; frame_number derives it from the number at the end of the
    file name, normalised over all splits (the Dry Ice scene's json times are normalised per split)."""
    splits: tuple[str, ...] = ("train", "test")
    """Splits to load, of train, val, test."""
    max_frames: Annotated[int, AT_LEAST_ONE] | None = None
    """Keep an evenly spaced subset of at most this many frames per split (tests, quick looks); none = all."""
    train_until: Annotated[float, UNIT] | None = None
    """Future prediction: train on frames with time <= this and evaluate (val, test) on frames with time > this, in
    dataset time [0, 1] (the paper's protocol: 0.8); none = every frame of each split."""
    load_masks: bool = True
    """Read motion masks where the dataset ships them (they drive static/dynamic decoupling and the flow target)."""
    # A dynamic dataset without per-frame times is almost always a mistake, so it is an error unless allowed.
    allow_missing_time: bool = False
    """Accept frames without a time: then time = index / (n - 1) within each split."""
    hypernerf_split: HyperNerfSplit = "vrig"
    """HyperNeRF / Nerfies: vrig (the second camera is the test set) or interp (every k-th frame trains)."""
    hypernerf_image_scale: Annotated[int, AT_LEAST_ONE] = 2
    """HyperNeRF / Nerfies: which rgb/{1,2,4}x folder to read."""
    hypernerf_interp_interval: Annotated[int, AT_LEAST_ONE] = 4
    """HyperNeRF "interp": train on every k-th frame, test on the midpoints (an even k >= 2)."""
    num_workers: Annotated[int, NON_NEGATIVE] = 0
    """Image-decoding threads; 0 = min(8, CPU count)."""
    progress: bool = True
    """Show a progress bar while images load."""

    def __post_init__(self) -> None:
        validate_config(self)
        if isinstance(self.downscale, tuple) and (len(self.downscale) != 2 or any(int(v) != v for v in self.downscale)):
            raise ValueError(f"DataConfig.downscale size must be (width, height) in whole pixels, got {self.downscale}")
        unknown = [s for s in self.splits if s not in SPLIT_NAMES]
        if unknown or not self.splits:
            raise ValueError(f"DataConfig.splits must be a non-empty subset of {SPLIT_NAMES}, got {self.splits}")
        if self.hypernerf_interp_interval < 2 or self.hypernerf_interp_interval % 2:
            raise ValueError(
                f"DataConfig.hypernerf_interp_interval must be an even number >= 2 (the test frame sits midway "
                f"between two training frames), got {self.hypernerf_interp_interval}"
            )

    @property
    def root(self) -> Path:
        return Path(self.path)

    @property
    def background_rgb(self) -> tuple[float, float, float]:
        return (1.0, 1.0, 1.0) if self.background == "white" else (0.0, 0.0, 0.0)

    def resample_for(self, layout: str) -> Resample:
        """``resample`` for a scene of this layout (``SceneData.info["layout"]``): auto is D-NeRF's protocol
        (area-rgba) on D-NeRF scenes, whose published tables were scored on images shrunk so, lanczos elsewhere."""
        if self.resample != "auto":
            return self.resample
        return "area-rgba" if layout == "dnerf" else "lanczos"

    def target_size(self, width: int, height: int) -> tuple[int, int]:
        """The (width, height) an image of the given size is resized to."""
        if isinstance(self.downscale, tuple):
            return int(self.downscale[0]), int(self.downscale[1])
        factor = float(self.downscale)
        return max(1, round(width / factor)), max(1, round(height / factor))


def parse_downscale(text: str) -> float | tuple[int, int]:
    """Parse a command-line downscale: ``"2"`` (factor) or ``"400x400"`` (width x height)."""
    text = text.strip().lower()
    try:
        if "x" in text:
            w, h = text.split("x")
            return int(w), int(h)
        return float(text)
    except ValueError:
        raise ValueError(f"downscale must be a factor such as '2' or a size such as '400x400', got {text!r}") from None


# ---------------------------------------------------------------------------------------------------------------
# loaded data
# ---------------------------------------------------------------------------------------------------------------
@dataclass(eq=False)
class Frame:
    """One training or evaluation image with its camera and time.

    ``image_u8`` is the stored form; use :attr:`image` for a float32 tensor in [0, 1].
    """

    camera: Camera
    time: float  # in [0, 1]
    image_u8: Tensor  # [H, W, 3] uint8, composited on the scene background
    mask: Tensor | None = None  # [H, W] bool, True = dynamic (moving) pixel
    name: str = ""  # e.g. "train/0002" or a HyperNeRF item id
    path: Path | None = None  # the image file it came from
    depth: Tensor | None = None  # [H, W] float32 camera-z depth from the dataset (0 = unknown), when it ships one

    @property
    def image(self) -> Tensor:
        """[H, W, 3] float32 in [0, 1] (a new tensor each call)."""
        return self.image_u8.to(torch.float32).div_(255.0)

    @property
    def width(self) -> int:
        return int(self.image_u8.shape[1])

    def to(self, device: torch.device | str) -> "Frame":
        """The frame with its camera, image, mask and depth on ``device`` (itself when they are there already)."""
        if self.image_u8.device == torch.device(device):
            return self

        def move(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(device)

        return Frame(self.camera.to(device), self.time, self.image_u8.to(device), move(self.mask), self.name, self.path, move(self.depth))

    @property
    def height(self) -> int:
        return int(self.image_u8.shape[0])


@dataclass(frozen=True)
class PointCloud:
    """Initial points for the Gaussians: positions [P, 3] float32 and colours [P, 3] float32 in [0, 1] or None."""

    xyz: Tensor
    rgb: Tensor | None = None

    def __post_init__(self) -> None:
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise ValueError(f"PointCloud.xyz must be [P, 3], got {tuple(self.xyz.shape)}")
        if self.rgb is not None and self.rgb.shape != self.xyz.shape:
            raise ValueError(f"PointCloud.rgb must match xyz {tuple(self.xyz.shape)}, got {tuple(self.rgb.shape)}")

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class SceneBounds:
    """Where the scene is, for Gaussian initialisation and size thresholds.

    ``center`` / ``radius`` follow 3DGS's ``getNerfppNorm``: the mean of the training camera centres and 1.1 x
    the largest distance of a training camera from it. ``radius`` is what 3DGS calls the *cameras extent*
    (densification and pruning thresholds are fractions of it). ``points_min`` / ``points_max`` is the
    axis-aligned box of the initial point cloud when there is one.
    """

    center: Tensor  # [3] float32
    radius: float
    points_min: Tensor | None = None  # [3] float32
    points_max: Tensor | None = None  # [3] float32

    @property
    def extent(self) -> float:
        return self.radius


def compute_bounds(camera_centers: Tensor, points: PointCloud | None = None) -> SceneBounds:
    """Scene bounds from training camera centres [N, 3] (and the point cloud's box, if any).

    A degenerate rig (one camera, or a camera that never moves) would give radius 0 and break every threshold
    that is a fraction of it; then the half-diagonal of the point box is used, or 1.0 without points.
    """
    centers = camera_centers.to(torch.float64).reshape(-1, 3)
    center = centers.mean(dim=0)
    radius = 1.1 * float((centers - center).norm(dim=1).max()) if len(centers) else 0.0
    pmin = pmax = None
    if points is not None and len(points) > 0:
        pmin, pmax = points.xyz.min(dim=0).values, points.xyz.max(dim=0).values
    if radius < 1e-6:
        radius = 0.5 * float((pmax - pmin).norm()) if pmin is not None else 0.0
        radius = radius if radius > 1e-6 else 1.0
        logger.warning("training cameras do not move; using scene radius %.4g instead of the camera spread", radius)
    return SceneBounds(center.to(torch.float32), radius, pmin, pmax)


@dataclass(eq=False)
class SceneData:
    """Everything a reader loads from one dataset folder.

    ``splits`` maps a split name ("train", "val", "test") to its frames in file order. ``time_source`` says
    where the times came from ("json", "frame_number", "index" or "metadata.json:<key>").
    """

    root: Path
    kind: str  # "blender" (D-NeRF, BlenderNeRF, PIDG) or "hypernerf"
    splits: dict[str, list[Frame]]
    background: Tensor  # [3] float32 in [0, 1]
    bounds: SceneBounds
    time_source: str
    points3d: PointCloud | None = None
    near_far: tuple[float, float] | None = None  # the dataset's depth range when it gives one (HyperNeRF)
    info: dict[str, object] = field(default_factory=dict)  # reader-specific facts, e.g. image scale

    @property
    def name(self) -> str:
        return self.root.name

    def to(self, device: torch.device | str) -> "SceneData":
        """The scene with every frame (images stay uint8: 4x less device memory) and the background on ``device``;
        itself on the device it is on. The point cloud stays where it is (it only seeds the Gaussians)."""
        if self.background.device == torch.device(device):
            return self
        splits = {name: [frame.to(device) for frame in frames] for name, frames in self.splits.items()}
        return replace(self, splits=splits, background=self.background.to(device))

    def frames(self, split: str) -> list[Frame]:
        if split not in self.splits:
            raise KeyError(f"split {split!r} was not loaded; loaded splits: {sorted(self.splits)}")
        return self.splits[split]

    @property
    def train(self) -> list[Frame]:
        return self.frames("train")

    @property
    def test(self) -> list[Frame]:
        return self.frames("test")

    def split_in_time(self, train_until: float) -> "SceneData":
        """Future prediction: training frames with time <= ``train_until``, evaluation frames (val, test) after it.

        Scene bounds and time normalisation stay those of the whole recording (they come from the cameras and the
        frame list, not from pixels), so a split scene has the same coordinates and times as the full one.
        """
        splits = {
            name: [f for f in frames if (f.time <= train_until) == (name == "train")] for name, frames in self.splits.items()
        }
        for name, frames in splits.items():
            if self.splits[name] and not frames:
                side = "at or before" if name == "train" else "after"
                raise DatasetError(self.root, f"no {name} frame has a time {side} train_until={train_until}")
        return replace(self, splits=splits, info={**self.info, "train_until": train_until})

    def times(self, split: str) -> Tensor:
        """[N] float32 times of a split's frames."""
        return torch.tensor([f.time for f in self.frames(split)], dtype=torch.float32)

    def summary(self) -> str:
        parts = [
            f"{s}: {len(f)} frames {f[0].width}x{f[0].height}" if f else f"{s}: 0 frames"
            for s, f in self.splits.items()
        ]
        pts = f", {len(self.points3d)} points" if self.points3d is not None else ""
        return f"{self.name} ({self.kind}; {'; '.join(parts)}; time from {self.time_source}{pts})"
