"""Render core: camera, EWA projection, compositing (numba CPU kernel, torch reference, gsplat on CUDA)."""
from pidg.render.api import RenderOutput, rasterize
from pidg.render.camera import Camera
from pidg.render.projection import Projection, project_gaussians

__all__ = ["Camera", "Projection", "RenderOutput", "project_gaussians", "rasterize"]
