"""``pidg make-scene``: PIDG-style dynamic scenes from Blender's own solvers, with ground-truth motion.

bpy (Blender as a Python module) is optional (``pip install -e ".[scenes]"``): only :mod:`pidg.scenes.blender_build`
uses it, inside its functions, so this package and the ``pidg`` command import without it and ``pidg make-scene``
says in one line what to install. :mod:`pidg.scenes.ground_truth` (ray casting, flow, velocities) and
:mod:`pidg.scenes.verify` need no bpy.
"""
from pidg.scenes.blender_build import BPY_HINT, KINDS, TEXTURES
from pidg.scenes.make_scene import SceneOptions, make_scene, parse_resolution
from pidg.scenes.verify import summary_lines, verify_dataset

__all__ = ["BPY_HINT", "KINDS", "TEXTURES", "SceneOptions", "make_scene", "parse_resolution", "summary_lines", "verify_dataset"]
