"""``pidg view``: an interactive web viewer of a trained run (viser in the browser, pidg's renderer behind it).

viser is optional (``pip install 'pidg[view]'``): it is imported when a viewer starts, so the rest of pidg works
without it and ``pidg view`` says in one line what to install.
"""
from pidg.viewer.frames import Quality, ViewRenderer, camera_from_pose, pose_of_camera, view_modes
from pidg.viewer.server import VISER_HINT, FrameStat, Viewer, ViewerOptions, check_port, serve_run, start_viewer

__all__ = [
    "VISER_HINT",
    "FrameStat",
    "Quality",
    "ViewRenderer",
    "Viewer",
    "ViewerOptions",
    "camera_from_pose",
    "check_port",
    "pose_of_camera",
    "serve_run",
    "start_viewer",
    "view_modes",
]
