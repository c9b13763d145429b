"""Static/dynamic decoupling (PIDG stage 2, NOTES.md section 3), as a training hook that owns the split.

At the end of densification every Gaussian is voted dynamic or static. With motion masks (PIDG scenes), it is
dynamic if its centre lands inside the 2D motion mask in more than ``vote`` of the training views that see it.
Without masks (D-NeRF, HyperNeRF) the learned motion decides: it is dynamic if, in more than ``vote`` of the views
that see it, the deformation moves its projected centre at least ``motion_px`` pixels away from where its
time-averaged position projects. From then on the scene model keeps static Gaussians out of the deformation
(``DynamicGaussians.at``) and gives them no velocity; they still refine their rendering parameters.

At the switch, static Gaussians take their time-averaged deformed state (position, orientation, scale) as their
canonical one: switching the deformation off must not move them (it did: they jumped back to canonical positions
that no training view had ever seen them at). Only this hook sets the split (``DynamicGaussians.set_dynamic_mask``);
the model stores it as a per-Gaussian row so densification and checkpoints carry it.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.models.deformation import DeformedGaussians
from pidg.models.dynamic_gaussians import DynamicGaussians

logger = logging.getLogger(__name__)

MAX_AVERAGE_TIMES = 64  # the time average samples at most this many training times (cost: one deformation each)


@torch.no_grad()
def time_averaged_state(model: DynamicGaussians, times: Sequence[float]) -> DeformedGaussians:
    """Every Gaussian's deformed state averaged over ``times``: mean position and log-scale, and the normalised mean
    of its quaternions taken on the canonical quaternion's side (q and -q are one rotation)."""
    times = sorted(set(times))
    if len(times) > MAX_AVERAGE_TIMES:
        times = [times[round(i * (len(times) - 1) / (MAX_AVERAGE_TIMES - 1))] for i in range(MAX_AVERAGE_TIMES)]
    reference = model.gaussians.params["quats"]
    means = torch.zeros_like(model.gaussians.params["means"])
    quats, log_scales = torch.zeros_like(reference), torch.zeros_like(means)
    for t in times:
        state = model.at(t)
        means += state.means
        sign = torch.where((state.quats * reference).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        quats += sign * state.quats
        log_scales += state.log_scales
    n = float(len(times))
    return DeformedGaussians(means / n, torch.nn.functional.normalize(quats, dim=-1), log_scales / n)


@torch.no_grad()
def _vote(model: DynamicGaussians, frames: Sequence[Frame], vote: float, hit: Callable[[Frame, Tensor, Tensor], Tensor]) -> Tensor:
    """[N] bool: ``hit(frame, pixels [M, 2], visible indices [M])`` is True in more than ``vote`` of the frames in
    which a Gaussian's centre at the frame's time is in front of the camera and inside the image."""
    inside = torch.zeros(model.num_gaussians, device=model.device)
    seen = torch.zeros(model.num_gaussians, device=model.device)
    for frame in frames:
        cam = frame.camera
        uv, z = cam.project_points(model.at(frame.time).means)
        u, v = uv.unbind(-1)
        ok = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        seen[ok] += 1
        inside[ok] += hit(frame, uv[ok], ok.nonzero().squeeze(1)).float()
    return inside > vote * seen.clamp_min(1)


def vote_dynamic(model: DynamicGaussians, frames: Sequence[Frame], vote: float) -> Tensor:
    """[N] bool from motion masks: True where a Gaussian's centre lands inside the frame's mask in more than
    ``vote`` of the masked frames that see it."""
    masked = [f for f in frames if f.mask is not None]

    def in_mask(frame: Frame, uv: Tensor, _: Tensor) -> Tensor:
        assert frame.mask is not None
        return frame.mask.to(uv.device)[uv[:, 1].long(), uv[:, 0].long()]

    return _vote(model, masked, vote, in_mask)


def vote_moving(model: DynamicGaussians, frames: Sequence[Frame], vote: float, average: Tensor, motion_px: float) -> Tensor:
    """[N] bool from the learned motion: True where, in more than ``vote`` of the frames that see it, a Gaussian's
    centre projects at least ``motion_px`` pixels from where its time-averaged position ``average`` [N, 3] does."""

    def moved(frame: Frame, uv: Tensor, index: Tensor) -> Tensor:
        uv_rest, _ = frame.camera.project_points(average[index])
        return (uv - uv_rest).norm(dim=-1) >= motion_px

    return _vote(model, frames, vote, moved)


class StaticDynamicDecoupling:
    """Splits the Gaussians once: after the step before ``at_step`` (the end of densification) by the motion masks
    when the training frames carry them, otherwise by the learned motion (``motion_px`` > 0; 0: no split) after the
    step before ``motion_at_step`` (default ``at_step``). A run with a static warm-up should give its deformation as
    many steps to learn the motion as a run without one: split by motion that much later (the trainer passes
    ``densify.stop + static_warmup``). The learned-motion split is tried at that step only, and not made if it finds
    no moving Gaussian: the deformation has not learned the motion, and the split would freeze it for good (it did:
    the MLP rows of the suite trained a static scene after their 500-step warm-up)."""

    def __init__(self, at_step: int, vote: float = 0.4, motion_px: float = 2.0, motion_at_step: int | None = None) -> None:
        self.at_step = at_step
        self.vote = vote
        self.motion_px = motion_px
        self.motion_at_step = at_step if motion_at_step is None else motion_at_step

    def step_post_backward(self, model: DynamicGaussians, frames: Sequence[Frame], step: int) -> bool:
        """Decouple if it is time and it has not happened yet; returns whether it did."""
        if model.dynamic_mask is not None:
            return False
        masks = any(f.mask is not None for f in frames)
        if masks and step + 1 < self.at_step:
            return False
        if not masks and step + 1 != max(self.motion_at_step, 1):  # tried at that step only (resumes alike)
            return False
        if not masks and self.motion_px <= 0:
            return False
        average = time_averaged_state(model, [f.time for f in frames])
        if masks:
            dynamic = vote_dynamic(model, frames, self.vote)
        else:
            dynamic = vote_moving(model, frames, self.vote, average.means, self.motion_px)
            if not bool(dynamic.any()):
                logger.info("no static/dynamic decoupling at step %d: no Gaussian moves %g px in the learned motion", step, self.motion_px)
                return False
        model.set_dynamic_mask(dynamic, static_state=average)
        logger.info(
            "static/dynamic decoupling at step %d (%s): %d dynamic, %d static Gaussians", step,
            "motion masks" if masks else f"learned motion >= {self.motion_px:g} px", int(dynamic.sum()), int((~dynamic).sum()),
        )
        return True
