"""Dense optical flow between two images, the forward-backward consistency check, and bilinear lookups.

Conventions used throughout :mod:`pidg.flow`: a flow field is a tensor [H, W, 2] of (dx, dy) in pixels, stored at
the pixel centres p = (j + 0.5, i + 0.5) of its *source* image (as :class:`pidg.render.camera.Camera`); the
flow from image 0 to image 1 maps p in image 0 to p + f(p) in image 1.

Estimators: OpenCV's DIS (default; ~10 ms per 480x270 pair on one core), DeepFlow and Dual TV-L1 (the paper
used TV-L1 for its synthetic data; both ~0.5 s per pair), and RAFT only from weights already on disk.
"""
from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pidg.flow.config import FlowConfig

ImagePairFlow = Callable[[np.ndarray, np.ndarray], np.ndarray]  # uint8 RGB [H, W, 3] x 2 -> float32 [H, W, 2]
_RAFT_MULTIPLE = 8  # RAFT needs image sides divisible by 8


class FlowEstimatorUnavailable(RuntimeError):
    """The chosen estimator cannot run here (missing package or weights); the message says what to do."""


@dataclass(frozen=True)
class FlowEstimator:
    """A named flow function with the settings that determine its output (they go into the cache hash)."""

    name: str
    settings: dict[str, Any]
    compute: ImagePairFlow = field(repr=False, compare=False)

    def __call__(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """Flow from ``image0`` to ``image1`` (uint8 RGB [H, W, 3]) as float32 [H, W, 2]."""
        flow = self.compute(image0, image1)
        h, w = image0.shape[:2]
        if flow.shape != (h, w, 2):
            raise RuntimeError(f"flow estimator {self.name!r} returned shape {flow.shape}, expected {(h, w, 2)}")
        return np.ascontiguousarray(flow, dtype=np.float32)


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as err:
        raise FlowEstimatorUnavailable(
            "optical flow needs OpenCV with the contrib modules: pip install opencv-contrib-python-headless"
        ) from err
    return cv2


def _gray(image: np.ndarray) -> np.ndarray:
    cv2 = _cv2()
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)


def _opencv_flow(algorithm: Any) -> ImagePairFlow:
    """Wrap an OpenCV ``DenseOpticalFlow`` object (grayscale uint8 in, float32 flow out)."""

    def compute(image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        return algorithm.calc(_gray(image0), _gray(image1), None)

    return compute


def _optflow_module() -> Any:
    cv2 = _cv2()
    if not hasattr(cv2, "optflow"):
        raise FlowEstimatorUnavailable(
            "DeepFlow and Dual TV-L1 live in OpenCV's contrib modules: replace opencv-python(-headless) by "
            "opencv-contrib-python-headless"
        )
    return cv2.optflow


def _sha1_file(path: Path) -> str:
    digest = hashlib.sha1()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _load_raft(path: Path) -> Callable[..., Any]:
    """RAFT from a local file: a ``torch.export`` program (``.pt2``), a TorchScript module, or a state dict for
    torchvision's ``raft_large``. Called as ``model(image0, image1)`` on [1, 3, H, W] images in [-1, 1]."""
    if path.suffix == ".pt2":
        return torch.export.load(str(path)).module()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit is deprecated but still reads old files
        try:
            return torch.jit.load(str(path), map_location="cpu").eval()
        except (RuntimeError, ValueError):
            pass  # not TorchScript: try a torchvision state dict
    try:
        from torchvision.models.optical_flow import raft_large
    except ImportError as err:
        raise FlowEstimatorUnavailable(
            f"{path} is neither a torch.export (.pt2) nor a TorchScript RAFT, and loading a RAFT state dict needs "
            "torchvision (pip install torchvision built for your torch)"
        ) from err
    model = raft_large(weights=None, progress=False)
    model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    return model.eval()


def _raft_flow(path: Path | None) -> ImagePairFlow:
    if path is None or not Path(path).is_file():
        where = "no path given" if path is None else f"{path} does not exist"
        raise FlowEstimatorUnavailable(
            f"estimator 'raft' needs RAFT weights on this machine ({where}); set --flow.raft_weights to a "
            "torch.export RAFT program (.pt2), a TorchScript RAFT or a torchvision raft_large state dict. Nothing is "
            "downloaded; use --flow.estimator dis (default), deepflow or tvl1 otherwise."
        )
    model = _load_raft(Path(path))

    def to_input(image: np.ndarray, pad: tuple[int, int, int, int]) -> Tensor:
        t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).unsqueeze(0).float()
        return F.pad(t / 127.5 - 1.0, pad, mode="replicate")

    def compute(image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        h, w = image0.shape[:2]
        pad = (0, -w % _RAFT_MULTIPLE, 0, -h % _RAFT_MULTIPLE)
        with torch.no_grad():
            out = model(to_input(image0, pad), to_input(image1, pad))
        flow = out[-1] if isinstance(out, (list, tuple)) else out  # torchvision returns every refinement
        return flow[0, :, :h, :w].permute(1, 2, 0).numpy()

    return compute


def upsampled(compute: ImagePairFlow, factor: int) -> ImagePairFlow:
    """``compute`` run on both images enlarged ``factor`` times (bicubic), its flow brought back to the original
    pixel grid: the mean over each factor x factor block (whose centres average to the original pixel's centre),
    divided by ``factor`` (high-resolution pixels -> original pixels)."""
    if factor == 1:
        return compute

    def enlarge(image: np.ndarray) -> np.ndarray:
        x = torch.tensor(image, dtype=torch.float32).permute(2, 0, 1)[None]  # a copy: images may be read-only
        big = F.interpolate(x, scale_factor=factor, mode="bicubic", align_corners=False)
        return big[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()

    def run(image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        flow = torch.from_numpy(np.ascontiguousarray(compute(enlarge(image0), enlarge(image1)), dtype=np.float32))
        small = F.avg_pool2d(flow.permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0) / factor
        return small.numpy()

    return run


def make_estimator(config: FlowConfig) -> FlowEstimator:
    """The estimator ``config.estimator`` names, the OpenCV ones run at ``config.upsample`` times the images'
    resolution (RAFT, a network trained at native resolution, at the images' own); :class:`FlowEstimatorUnavailable`
    if it cannot run here."""
    estimator = _make_estimator(config)
    if config.upsample == 1 or estimator.name == "raft":
        return estimator  # the settings (and so the flow cache's keys) of runs made before the option existed
    settings = {**estimator.settings, "upsample": config.upsample}
    return FlowEstimator(estimator.name, settings, upsampled(estimator.compute, config.upsample))


def _make_estimator(config: FlowConfig) -> FlowEstimator:
    name = config.estimator
    if name == "dis":
        cv2 = _cv2()
        preset = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                  "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}[config.dis_preset]
        settings = {"preset": config.dis_preset, "opencv": cv2.__version__}
        return FlowEstimator(name, settings, _opencv_flow(cv2.DISOpticalFlow_create(preset)))
    if name == "deepflow":
        optflow = _optflow_module()
        return FlowEstimator(name, {"opencv": _cv2().__version__}, _opencv_flow(optflow.createOptFlow_DeepFlow()))
    if name == "tvl1":
        optflow = _optflow_module()
        return FlowEstimator(name, {"opencv": _cv2().__version__}, _opencv_flow(optflow.DualTVL1OpticalFlow_create()))
    if name == "raft":
        compute = _raft_flow(config.raft_weights)
        assert config.raft_weights is not None
        return FlowEstimator(name, {"weights_sha1": _sha1_file(Path(config.raft_weights))}, compute)
    raise ValueError(f"unknown flow estimator {name!r}")


# ---------------------------------------------------------------------------------------------------------------
# pixel grids and lookups (torch, differentiable, any float dtype)
# ---------------------------------------------------------------------------------------------------------------
def pixel_centers(height: int, width: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
    """[H, W, 2] pixel centres (j + 0.5, i + 0.5), the camera convention."""
    ys = torch.arange(height, dtype=dtype, device=device) + 0.5
    xs = torch.arange(width, dtype=dtype, device=device) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], dim=-1)


def sample_bilinear(field: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Bilinear lookup of ``field`` [H, W, C] at pixel positions ``points`` [..., 2] (centre convention).

    Returns (values [..., C], inside [...]). ``inside`` is True where the position lies in the image domain
    [0, W] x [0, H]; in the half-pixel border ring outside the outermost centres the edge value is repeated.
    """
    h, w, c = field.shape
    lead = points.shape[:-1]
    grid = points.reshape(1, 1, -1, 2).to(field.dtype)
    scale = grid.new_tensor([2.0 / w, 2.0 / h])
    values = F.grid_sample(
        field.permute(2, 0, 1).unsqueeze(0), grid * scale - 1.0, mode="bilinear", padding_mode="border",
        align_corners=False,
    )
    values = values.reshape(c, -1).T.reshape(*lead, c)
    x, y = points[..., 0], points[..., 1]
    inside = (x >= 0) & (x <= w) & (y >= 0) & (y <= h) & torch.isfinite(points).all(-1)
    return values, inside


def sample_mask(mask: Tensor, points: Tensor) -> Tensor:
    """Bool mask [H, W] looked up bilinearly at ``points``: True only where every neighbour with a non-zero
    weight is True and the position is inside the image (a flow interpolated there mixes no invalid value)."""
    values, inside = sample_bilinear(mask.to(points.dtype).unsqueeze(-1), points)
    return inside & (values[..., 0] > 1.0 - 1e-6)


# ---------------------------------------------------------------------------------------------------------------
# forward-backward consistency
# ---------------------------------------------------------------------------------------------------------------
def forward_backward_consistency(forward: Tensor, backward: Tensor, alpha: float = 0.01, beta: float = 0.5) -> Tensor:
    """Where the flow ``forward`` [H, W, 2] (image 0 -> 1) is trustworthy: [H, W] bool on image 0's pixels.

    The standard test (Sundaram, Brox & Keutzer 2010; used by UnFlow, RAFT-based pipelines...): following the
    forward flow and then the backward flow (image 1 -> 0, looked up bilinearly at p + f(p)) must come back to p,
    up to a tolerance that grows with the motion,

        |f(p) + b(p + f(p))|^2 < alpha (|f(p)|^2 + |b(p + f(p))|^2) + beta,

    and p + f(p) must land inside image 1. Pixels that fail are occluded in image 1 or mismatched. For the
    backward flow's mask swap the arguments.
    """
    if forward.shape != backward.shape or forward.dim() != 3 or forward.shape[-1] != 2:
        raise ValueError(f"flows must both be [H, W, 2], got {list(forward.shape)} and {list(backward.shape)}")
    h, w, _ = forward.shape
    target = pixel_centers(h, w, forward.dtype, forward.device) + forward
    b_at, inside = sample_bilinear(backward, target)
    err = (forward + b_at).square().sum(-1)
    tolerance = alpha * (forward.square().sum(-1) + b_at.square().sum(-1)) + beta
    return inside & (err < tolerance)
