"""Render core: camera, EWA projection, compositing (numba CPU kernel, torch reference, gsplat on CUDA)."""
from pidg.render.api import RenderBackend, project, rasterize, resolve_backend
from pidg.render.camera import Camera
from pidg.render.output import OPAQUE_ALPHA, RenderOutput
from pidg.render.projection import Projection, project_gaussians

__all__ = [
    "OPAQUE_ALPHA", "Camera", "Projection", "RenderBackend", "RenderOutput", "project", "project_gaussians", "rasterize", "resolve_backend",
]
