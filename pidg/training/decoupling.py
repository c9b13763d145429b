"""Static/dynamic decoupling (PIDG stage 2, NOTES.md section 3), as a training hook that owns the split.

At the end of densification every Gaussian is voted dynamic or static: it is dynamic if its centre lands inside
the 2D motion mask in more than ``vote`` of the training views that see it. From then on the scene model keeps
static Gaussians out of the deformation (``DynamicGaussians.at``) and gives them no velocity; they still refine
their rendering parameters. Only this hook sets the split (``DynamicGaussians.set_dynamic_mask``); the model
stores it as a per-Gaussian row so densification and checkpoints carry it.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from pidg.data.scene import Frame
from pidg.models.dynamic_gaussians import DynamicGaussians

logger = logging.getLogger(__name__)


@torch.no_grad()
def vote_dynamic(model: DynamicGaussians, frames: Sequence[Frame], vote: float) -> Tensor:
    """[N] bool: True where a Gaussian's centre at each frame's time lands inside the frame's motion mask in more
    than ``vote`` of the masked frames in which it is in front of the camera and inside the image."""
    inside = torch.zeros(model.num_gaussians, device=model.device)
    seen = torch.zeros(model.num_gaussians, device=model.device)
    for frame in frames:
        if frame.mask is None:
            continue
        cam = frame.camera
        uv, z = cam.project_points(model.at(frame.time).means)
        u, v = uv.unbind(-1)
        ok = (z > cam.near) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        seen[ok] += 1
        inside[ok] += frame.mask.to(model.device)[v[ok].long(), u[ok].long()].float()
    return inside > vote * seen.clamp_min(1)


class StaticDynamicDecoupling:
    """Splits the Gaussians once, after the step before ``at_step`` (the end of densification), if the training
    frames carry motion masks."""

    def __init__(self, at_step: int, vote: float = 0.4) -> None:
        self.at_step = at_step
        self.vote = vote

    def step_post_backward(self, model: DynamicGaussians, frames: Sequence[Frame], step: int) -> bool:
        """Decouple if it is time and it has not happened yet; returns whether it did."""
        if model.dynamic_mask is not None or step + 1 < self.at_step or not any(f.mask is not None for f in frames):
            return False
        dynamic = vote_dynamic(model, frames, self.vote)
        model.set_dynamic_mask(dynamic)
        logger.info("static/dynamic decoupling at step %d: %d dynamic, %d static Gaussians", step, int(dynamic.sum()), int((~dynamic).sum()))
        return True
