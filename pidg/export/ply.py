"""The Gaussians of a trained dynamic scene at one time, as a standard 3D Gaussian Splatting PLY.

The layout is the one the original 3DGS code writes and SuperSplat, gsplat's tools and the original viewers read:
one ``vertex`` element, binary little-endian, every property a float32, in this order::

    x y z                        position (the dataset's world units)
    nx ny nz                     normals, unused by splatting: zeros
    f_dc_0 f_dc_1 f_dc_2         degree-0 SH coefficient per colour channel (colour = SH + 0.5, as in pidg.render.sh)
    f_rest_0 ... f_rest_{3M-1}   the other M = (degree+1)^2 - 1 coefficients, channel-major: all of red's, then
                                 green's, then blue's (3DGS stores features_rest [N, M, 3] transposed to [N, 3, M])
    opacity                      logit of the opacity (the viewer applies the sigmoid)
    scale_0 scale_1 scale_2      log of the standard deviations along the Gaussian's axes (world units)
    rot_0 rot_1 rot_2 rot_3      rotation as a unit quaternion (w, x, y, z)

A file carries one time: the deformation is applied (static Gaussians stay canonical), so any static-splat viewer
shows the scene as pidg renders it at that time. SH degree: 3 by default (45 f_rest values, what the original
viewers expect); coefficients above the run's active degree are written as zeros, so the file renders exactly as
pidg does. The background colour and the time are not part of the format (the time is in a header comment).

Written with numpy (a structured array behind a text header) rather than with ``plyfile``: the format is a fixed
list of float32 columns, so writing it takes a dozen lines and adds no dependency to the package, and the tests read
the files back with ``plyfile``, an independent reader, to check the layout.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from pidg.device import Device
from pidg.export.run_model import check_time, open_run_model
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render.sh import num_sh_bases

DEFAULT_SH_DEGREE = 3
EXPORT_DIR = "export"  # inside the run folder, where exports go unless told otherwise


@dataclass
class SplatFrame:
    """The Gaussians at one dataset time in the PLY's quantities: float32 numpy arrays, N rows each."""

    time: float  # dataset time in [0, 1]
    means: np.ndarray  # [N, 3] world units
    sh_dc: np.ndarray  # [N, 3]
    sh_rest: np.ndarray  # [N, M, 3] coefficient-major (pidg's and gsplat's order), M = (sh_degree + 1)^2 - 1
    opacity_logits: np.ndarray  # [N]
    log_scales: np.ndarray  # [N, 3] log world units
    quats: np.ndarray  # [N, 4] unit (w, x, y, z)
    sh_degree: int

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])


def ply_property_names(sh_degree: int = DEFAULT_SH_DEGREE) -> list[str]:
    """The vertex properties of a 3DGS PLY of this SH degree, in file order."""
    rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


@torch.no_grad()
def splat_frame(model: DynamicGaussians, t: float, sh_degree: int = DEFAULT_SH_DEGREE) -> SplatFrame:
    """The model's Gaussians at dataset time ``t`` with ``sh_degree`` bands of colour (bands the run does not use
    are zero; a degree below the run's active one drops view-dependent colour)."""
    t = check_time(t, "time")
    if not 0 <= sh_degree <= 3:
        raise ValueError(f"SH degree {sh_degree}: must be 0, 1, 2 or 3")
    g = model.gaussians
    state = model.at(t)
    quats = state.quats / state.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    used = num_sh_bases(min(g.active_sh_degree, sh_degree)) - 1  # coefficients pidg renders with, beyond DC
    rest = g.params["sh_dc"].new_zeros(g.num_gaussians, num_sh_bases(sh_degree) - 1, 3)
    rest[:, :used] = g.params["sh_rest"][:, :used]

    def f32(x: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(x.detach().to("cpu", torch.float32).numpy())

    return SplatFrame(
        time=t, means=f32(state.means), sh_dc=f32(g.params["sh_dc"][:, 0]), sh_rest=f32(rest),
        opacity_logits=f32(g.params["opacity_logits"]), log_scales=f32(state.log_scales), quats=f32(quats), sh_degree=sh_degree,
    )


def write_splat_ply(frame: SplatFrame, path: Path | str) -> Path:
    """Write ``frame`` as a binary little-endian 3DGS PLY (atomically: a reader never sees half a file)."""
    path = Path(path)
    names = ply_property_names(frame.sh_degree)
    n = frame.num_gaussians
    columns = np.concatenate(
        [
            frame.means, np.zeros((n, 3), np.float32), frame.sh_dc,
            frame.sh_rest.transpose(0, 2, 1).reshape(n, -1),  # [N, M, 3] -> channel-major [N, 3M]
            frame.opacity_logits.reshape(n, 1), frame.log_scales, frame.quats,
        ],
        axis=1,
    ).astype("<f4")
    if columns.shape[1] != len(names):
        raise ValueError(f"SH coefficients do not match degree {frame.sh_degree}: {columns.shape[1]} columns for {len(names)} properties")
    header = [
        "ply", "format binary_little_endian 1.0",
        f"comment pidg export: Gaussians at dataset time t = {frame.time:.6g} (0 = first frame, 1 = last); "
        "positions in the dataset's world units",
        f"element vertex {n}",
        *(f"property float {name}" for name in names),
        "end_header",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(columns).tobytes())
    os.replace(tmp, path)
    return path


def sequence_times(model: DynamicGaussians) -> list[float]:
    """One time per training-frame interval from 0 to 1 (the run's frame times when they are evenly spaced)."""
    steps = max(1, round(1.0 / model.time_axis.frame_interval))
    return [i / steps for i in range(steps + 1)]


def export_ply(
    run_dir: Path | str, t: float, out: Path | str | None = None, device: Device = "auto", sh_degree: int = DEFAULT_SH_DEGREE
) -> Path:
    """The run's Gaussians at dataset time ``t`` as a 3DGS PLY (default ``RUN/export/gaussians_t<t>.ply``)."""
    t = check_time(t)
    model = open_run_model(run_dir, device)
    path = Path(out) if out is not None else Path(run_dir) / EXPORT_DIR / f"gaussians_t{t:.4f}.ply"
    return write_splat_ply(splat_frame(model, t, sh_degree), path)


def export_ply_sequence(
    run_dir: Path | str, times: Sequence[float] | None = None, out_dir: Path | str | None = None, device: Device = "auto",
    sh_degree: int = DEFAULT_SH_DEGREE,
) -> list[Path]:
    """One 3DGS PLY per time (default: :func:`sequence_times`) in ``out_dir`` (default ``RUN/export/sequence``):
    ``frame_0000.ply`` ..., and ``frames.json`` listing each file's dataset time, for per-frame splat players."""
    checked = [check_time(t, "--times value") for t in times] if times else None
    model = open_run_model(run_dir, device)
    checked = checked or sequence_times(model)
    out_dir = Path(out_dir) if out_dir is not None else Path(run_dir) / EXPORT_DIR / "sequence"
    paths = [write_splat_ply(splat_frame(model, t, sh_degree), out_dir / f"frame_{i:04d}.ply") for i, t in enumerate(checked)]
    index = {
        "format": "3dgs-ply",
        "time_unit": "dataset time in [0, 1] (0 = first frame, 1 = last)",
        "position_unit": "dataset world units",
        "sh_degree": sh_degree,
        "gaussians": model.num_gaussians,
        "frames": [{"file": p.name, "time": t} for p, t in zip(paths, checked)],
    }
    (out_dir / "frames.json").write_text(json.dumps(index, indent=2))
    return paths
