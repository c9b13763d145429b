"""Render core: camera, EWA projection, compositing (numba CPU kernel, torch reference, gsplat on CUDA)."""
from pidg.render.api import PreparedRender, RenderBackend, composite, gaussians_reaching, prepare_render, project, rasterize, resolve_backend
from pidg.render.camera import Camera
from pidg.render.output import OPAQUE_ALPHA, RenderOutput
from pidg.render.projection import Projection, project_gaussians

__all__ = [
    "OPAQUE_ALPHA", "Camera", "PreparedRender", "Projection", "RenderBackend", "RenderOutput", "composite", "gaussians_reaching",
    "prepare_render", "project", "project_gaussians", "rasterize", "resolve_backend",
]
