"""The Blender side of ``pidg make-scene``: scenes built from Blender's own solvers, their evaluated meshes, renders,
and Blender's independent checks of the ground truth. Imports bpy (installed by ``pip install -e ".[scenes]"``).

Every scene: a textured floor (8 x 8 world units at z = 0, world z up), a static textured block, a sun and a dim
sky light, and the dynamic objects of its kind, all textured with procedural patterns (:data:`TEXTURES`) fixed to the
surface (object or UV coordinates), so optical flow has something to track:

* ``rigid``: five objects (cube, sphere, cylinder, cone, small cube) dropped with random tilts, stacked so that they
  hit each other, bouncing on the floor (Blender's rigid-body world, Bullet; 10 substeps a frame);
* ``cloth``: a square cloth (28 x 28 vertices) falling over a sphere and draping onto the floor (cloth modifier;
  sphere and floor are collision objects);
* ``soft``: a soft ball (icosphere, 642 vertices) dropped onto a ramp, bouncing off it and squashing on the floor
  (soft-body modifier with edge springs, no goal);
* ``kinematic``: a keyframed Suzanne head on a smooth figure-eight path with hops, turning once and rocking (F-curves
  with sine modifiers: smooth to every order).

Blender frames: image i of the dataset is frame ``FIRST_IMAGE_FRAME + i``; the simulation starts at frame 1 (one
frame of lead-in, so the velocity at t = 0 has a past) and runs one frame past the last image (the last image's flow
and velocity need t + dt). Physics caches are baked (in memory) before anything reads them (see :func:`bake`).
"""
from __future__ import annotations

import contextlib
import functools
import math
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pidg.scenes.capture import Orbit
from pidg.scenes.ground_truth import camera_arrays
from pidg.render.camera import Camera

BPY_VERSION = "5.0.1"
"""The bpy release this module is written and tested against (pyproject's ``scenes`` extra pins it)."""
BPY_HINT = 'pidg make-scene needs bpy (Blender as a Python module, Python 3.11): pip install -e ".[scenes]"'
FIRST_IMAGE_FRAME = 2
FLOOR_SIZE = 8.0
FOV_X_DEG = 40.0


@contextlib.contextmanager
def quiet_fds() -> Iterator[list[str]]:
    """Send what C code prints on stdout/stderr (Blender's render log, bpy's import notes) to a temporary file; the
    list it yields receives that text, so a failure can still show it."""
    captured: list[str] = []
    with tempfile.TemporaryFile(mode="w+b") as sink:
        saved = [os.dup(1), os.dup(2)]
        try:
            for fd in (1, 2):
                os.dup2(sink.fileno(), fd)
            yield captured
        finally:
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
            sink.seek(0)
            captured.append(sink.read().decode(errors="replace"))


def import_bpy() -> Any:
    """The bpy module, or an ImportError whose message says in one line what to install.

    bpy 5.0.1 declares numpy < 2; with numpy 2 a bundled library's numpy bindings print a warning at import (hidden
    here) while everything make-scene uses works (checked by ``--verify``)."""
    try:
        with quiet_fds() as log:
            import bpy
    except ImportError as err:
        text = " ".join("".join(log).split())[-300:]
        raise ImportError(f"{BPY_HINT} ({err}{'; ' + text if text else ''})") from None
    return bpy


@dataclass
class BuiltScene:
    """A built Blender scene: its dynamic objects (object name, kind), static objects, camera and frame range."""

    dynamic: list[tuple[str, str]]
    static: list[str]
    camera: str
    orbit: Orbit
    sim_end: int  # last simulated Blender frame
    fps: int

    def image_frame(self, index: int) -> int:
        return FIRST_IMAGE_FRAME + index


# ---- materials ----------------------------------------------------------------------------------------------------
def _hsv(h: float, s: float, v: float) -> tuple[float, float, float, float]:
    """Linear RGBA of a colour given in HSV (h in turns)."""
    import colorsys

    return (*colorsys.hsv_to_rgb(h % 1.0, s, v), 1.0)


def _input(sockets: Any, name: str, kind: str | None = None) -> Any:
    """The enabled socket called ``name`` (of ``kind``, e.g. RGBA: mix nodes carry one per data type)."""
    for s in sockets:
        if s.name == name and s.enabled and (kind is None or s.type == kind):
            return s
    raise KeyError(f"no enabled socket {name!r} ({kind})")


#: ``make-scene --texture``: cells (random-coloured Voronoi cells, not periodic) or checker (a two-colour checker, the
#: scenes of docs/motion.md's tables measured before 2026-11-28), each the same size (``scale`` cells a unit: ~6
#: px across on the rigid bodies at the default 200 px) and times the same fine noise. The checker's period on screen
#: (~12 px) is about what a tumbling rigid body's surface moves in a frame: the optical flow then locks onto the
#: wrong period (docs/motion.md).
TEXTURES = ("cells", "checker")


def check_texture(texture: str) -> None:
    """One line naming the option when ``texture`` is not one of :data:`TEXTURES`."""
    if texture not in TEXTURES:
        raise ValueError(f"--texture {texture!r}: choose one of {', '.join(TEXTURES)}")


MaterialMaker = Callable[..., Any]  # textured_material with its texture chosen: (name, rng, coords=, scale=) -> material


def textured_material(name: str, rng: np.random.Generator, coords: str = "Object", scale: float = 4.0, texture: str = "cells") -> Any:
    """A diffuse material of ``texture`` (:data:`TEXTURES`) times coloured noise, in ``coords`` ("Object": fixed to a
    rigid object; "UV": fixed to a deforming surface), ``scale`` cells per unit (Object) or per UV tile. Both draw one
    number (the hue) from ``rng``, so the two textures give the same scene otherwise: the same simulation, cameras and
    ground-truth motion."""
    import bpy

    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 creates materials without nodes
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes.get("Principled BSDF") or nodes.new("ShaderNodeBsdfPrincipled")
    coord = nodes.new("ShaderNodeTexCoord")
    hue = float(rng.random())
    if texture == "checker":
        pattern = nodes.new("ShaderNodeTexChecker")
        pattern.inputs["Color1"].default_value = _hsv(hue, 0.75, 0.85)
        pattern.inputs["Color2"].default_value = _hsv(hue + 0.45, 0.55, 0.25)
        pattern.inputs["Scale"].default_value = scale
        links.new(coord.outputs[coords], pattern.inputs["Vector"])
        colour = pattern.outputs["Color"]
    else:  # each cell a random colour pulled towards the object's hue
        cells = nodes.new("ShaderNodeTexVoronoi")
        cells.inputs["Scale"].default_value = scale
        links.new(coord.outputs[coords], cells.inputs["Vector"])
        pattern = nodes.new("ShaderNodeMix")
        pattern.data_type, pattern.blend_type = "RGBA", "MIX"
        _input(pattern.inputs, "Factor", "VALUE").default_value = 0.85
        _input(pattern.inputs, "A", "RGBA").default_value = _hsv(hue, 0.7, 0.8)
        links.new(cells.outputs["Color"], _input(pattern.inputs, "B", "RGBA"))
        colour = _input(pattern.outputs, "Result", "RGBA")
    noise = nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 3.0 * scale
    noise.inputs["Detail"].default_value = 4.0
    mix = nodes.new("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    _input(mix.inputs, "Factor", "VALUE").default_value = 0.7
    links.new(coord.outputs[coords], noise.inputs["Vector"])
    links.new(colour, _input(mix.inputs, "A", "RGBA"))
    links.new(noise.outputs["Color"], _input(mix.inputs, "B", "RGBA"))
    links.new(_input(mix.outputs, "Result", "RGBA"), bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.65
    return mat


# ---- objects --------------------------------------------------------------------------------------------------------
def _add(op: str, material: Any, smooth: bool = False, **kwargs: Any) -> Any:
    """A primitive made by ``bpy.ops.mesh.<op>(**kwargs)``, with ``material``."""
    import bpy

    getattr(bpy.ops.mesh, op)(**kwargs)
    obj = bpy.context.active_object
    obj.data.materials.append(material)
    if smooth:
        obj.data.polygons.foreach_set("use_smooth", [True] * len(obj.data.polygons))
    return obj


def _rigid(obj: Any, kind: str, shape: str, restitution: float, friction: float = 0.5, mass: float = 1.0) -> None:
    import bpy

    bpy.context.view_layer.objects.active = obj
    bpy.ops.rigidbody.object_add(type=kind)
    rb = obj.rigid_body
    rb.collision_shape, rb.restitution, rb.friction = shape, restitution, friction
    if kind == "ACTIVE":
        rb.mass = mass


def _collider(obj: Any, thickness: float = 0.02, friction: float = 5.0, damping: float = 0.2) -> None:
    obj.modifiers.new("collision", "COLLISION")
    obj.collision.thickness_outer = thickness
    obj.collision.cloth_friction = friction
    obj.collision.damping = damping


def _cache_range(cache: Any, end: int) -> None:
    cache.frame_start, cache.frame_end = 1, end


def _common(scene: Any, rng: np.random.Generator, kind: str, material: MaterialMaker) -> tuple[Any, Any]:
    """Floor, static block, lights, world; returns (floor, block)."""
    import bpy

    floor = _add("primitive_plane_add", material("floor", rng, scale=1.5), size=FLOOR_SIZE)
    floor.name = "floor"
    block_at = {"rigid": (1.6, -1.3, 0.35), "cloth": (-1.5, 1.4, 0.35), "soft": (-1.2, -1.5, 0.35), "kinematic": (-1.5, 1.5, 0.35)}
    block = _add("primitive_cube_add", material("block", rng, scale=5.0), size=0.7, location=block_at[kind])
    block.name = "block"
    block.rotation_euler = (0.0, 0.0, float(rng.uniform(0, math.pi)))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy, sun.data.angle = 3.5, math.radians(8.0)
    sun.rotation_euler = (math.radians(40.0), math.radians(15.0), float(rng.uniform(0, 2 * math.pi)))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    background = world.node_tree.nodes.get("Background") or world.node_tree.nodes.new("ShaderNodeBackground")
    background.inputs["Color"].default_value = (0.35, 0.38, 0.45, 1.0)
    background.inputs["Strength"].default_value = 0.8
    scene.world = world
    return floor, block


def _build_rigid(scene: Any, rng: np.random.Generator, sim_end: int, material: MaterialMaker) -> list[tuple[str, str]]:
    import bpy

    floor = bpy.data.objects["floor"]
    _rigid(floor, "PASSIVE", "BOX", restitution=0.6)
    _rigid(bpy.data.objects["block"], "PASSIVE", "BOX", restitution=0.6)
    world = scene.rigidbody_world
    world.substeps_per_frame, world.solver_iterations = 10, 20
    _cache_range(world.point_cache, sim_end)
    specs = [  # (primitive, kwargs, collision shape, location, restitution)
        ("primitive_ico_sphere_add", {"subdivisions": 3, "radius": 0.32}, "SPHERE", (0.05, 0.0, 0.45), 0.8),
        ("primitive_cube_add", {"size": 0.5}, "BOX", (0.2, 0.1, 1.45), 0.6),
        ("primitive_cylinder_add", {"radius": 0.22, "depth": 0.6, "vertices": 24}, "CYLINDER", (-0.9, 0.5, 1.0), 0.7),
        ("primitive_cone_add", {"radius1": 0.3, "depth": 0.55, "vertices": 24}, "CONE", (0.8, 0.8, 1.8), 0.5),
        ("primitive_cube_add", {"size": 0.32}, "BOX", (-0.1, -0.15, 2.3), 0.6),
    ]
    dynamic = []
    for k, (op, kwargs, shape, location, restitution) in enumerate(specs):
        jitter = rng.uniform(-0.08, 0.08, size=3) * (1, 1, 0)
        obj = _add(op, material(f"body{k}", rng, scale=8.0), smooth=shape in ("SPHERE", "CYLINDER", "CONE"),
                   location=tuple(np.add(location, jitter)), rotation=tuple(rng.uniform(-0.6, 0.6, size=3)), **kwargs)
        obj.name = f"body{k}_{shape.lower()}"
        _rigid(obj, "ACTIVE", shape, restitution=restitution, mass=1.0 + k * 0.3)
        dynamic.append((obj.name, "rigid"))
    return dynamic


def _build_cloth(scene: Any, rng: np.random.Generator, sim_end: int, material: MaterialMaker) -> list[tuple[str, str]]:
    import bpy

    _collider(bpy.data.objects["floor"])
    _collider(bpy.data.objects["block"])
    sphere = _add("primitive_uv_sphere_add", material("sphere", rng, scale=6.0), smooth=True,
                  radius=0.5, segments=32, ring_count=16, location=(0.0, 0.0, 0.5))
    sphere.name = "sphere"
    _collider(sphere)
    cloth = _add("primitive_grid_add", material("cloth", rng, coords="UV", scale=8.0), smooth=True,
                 x_subdivisions=27, y_subdivisions=27, size=1.8, location=(0.12, -0.08, 1.35),
                 rotation=(float(rng.uniform(-0.25, 0.25)), float(rng.uniform(-0.25, 0.25)), float(rng.uniform(0, math.pi))))
    cloth.name = "cloth"
    mod = cloth.modifiers.new("cloth", "CLOTH")
    s = mod.settings
    s.quality, s.mass, s.air_damping = 6, 0.3, 1.0
    s.tension_stiffness = s.compression_stiffness = 15.0
    s.shear_stiffness, s.bending_stiffness = 5.0, 0.3
    mod.collision_settings.distance_min = 0.012
    _cache_range(mod.point_cache, sim_end)
    return [("cloth", "cloth")]


def _build_soft(scene: Any, rng: np.random.Generator, sim_end: int, material: MaterialMaker) -> list[tuple[str, str]]:
    import bpy

    for name in ("floor", "block"):
        _collider(bpy.data.objects[name], thickness=0.04, damping=0.05)
    ramp = _add("primitive_cube_add", material("ramp", rng, scale=5.0), size=1.0, location=(0.6, 0.0, 0.45),
                rotation=(0.0, math.radians(35.0), 0.0), scale=(1.0, 0.9, 0.15))
    ramp.name = "ramp"
    _collider(ramp, thickness=0.04, damping=0.05)
    ball = _add("primitive_ico_sphere_add", material("ball", rng, coords="UV", scale=6.0), smooth=True,
                subdivisions=3, radius=0.38, location=(0.45 + float(rng.uniform(-0.05, 0.05)), 0.0, 1.75))
    ball.name = "ball"
    mod = ball.modifiers.new("softbody", "SOFT_BODY")
    sb = ball.soft_body
    # friction is the medium's drag, 0: the ball keeps its speed between bounces; vertex collisions only (edge and
    # face collisions make the ball stick to the ramp)
    sb.use_goal, sb.mass, sb.friction = False, 1.0, 0.0
    sb.use_edges, sb.pull, sb.push, sb.damping, sb.bend = True, 0.9, 0.9, 0.5, 0.6
    sb.use_stiff_quads, sb.shear = True, 0.9
    sb.use_edge_collision = sb.use_face_collision = False
    sb.error_threshold, sb.step_min, sb.step_max = 0.02, 10, 300
    _cache_range(mod.point_cache, sim_end)
    return [("ball", "soft")]


def _fcurves(obj: Any) -> Any:
    """The F-curves of ``obj``'s action (Blender 5 keeps them per action slot)."""
    action = obj.animation_data.action
    if hasattr(action, "fcurves"):  # Blender < 5
        return action.fcurves
    from bpy_extras import anim_utils

    return anim_utils.action_get_channelbag_for_slot(action, obj.animation_data.action_slot).fcurves


def _build_kinematic(scene: Any, rng: np.random.Generator, sim_end: int, material: MaterialMaker) -> list[tuple[str, str]]:
    """A head on a figure-eight with hops, rocking and turning once: one keyframe per channel (its rest value) plus
    additive F-curve modifiers (sines; a straight line for the turn), so the path is smooth to every order and
    sub-frame evaluation is exact (Bezier keys would be C1 only: finite differences across a key lose an order)."""
    head = _add("primitive_monkey_add", material("head", rng, scale=7.0), smooth=True, size=0.8)
    head.name = "head"
    phase = float(rng.uniform(0, 2 * math.pi))
    head.location, head.rotation_euler = (0.0, 0.0, 0.9), (0.0, 0.0, phase)
    head.keyframe_insert("location", frame=1)
    head.keyframe_insert("rotation_euler", frame=1)
    per_frame = 2 * math.pi / (sim_end - 1)  # one cycle over the simulated frames 1..sim_end
    sines = {  # (channel, index): [(amplitude, cycles, phase)]
        ("location", 0): [(1.3, 1, phase)], ("location", 1): [(0.8, 2, 2 * phase)], ("location", 2): [(0.35, 3, 0.0)],
        ("rotation_euler", 0): [(0.35, 1, 0.0)], ("rotation_euler", 1): [(0.25, 2, 0.0)],
    }
    curves = _fcurves(head)
    for (path, index), terms in sines.items():
        for amplitude, cycles, offset in terms:
            mod = curves.find(path, index=index).modifiers.new("FNGENERATOR")
            mod.function_type, mod.amplitude, mod.use_additive = "SIN", amplitude, True
            mod.phase_multiplier, mod.phase_offset = cycles * per_frame, offset - cycles * per_frame  # 0 at frame 1
    turn = curves.find("rotation_euler", index=2).modifiers.new("GENERATOR")
    turn.use_additive, turn.coefficients = True, (-per_frame, per_frame)  # + 2 pi (frame - 1) / (sim_end - 1)
    return [("head", "kinematic")]


_BUILDERS = {"rigid": _build_rigid, "cloth": _build_cloth, "soft": _build_soft, "kinematic": _build_kinematic}
KINDS = tuple(_BUILDERS)


def build_scene(
    kind: str, n_images: int, seed: int, fps: int, static_camera: bool, texture: str = "cells", held_out_on_orbit: bool = False
) -> BuiltScene:
    """A fresh Blender scene of ``kind`` for ``n_images`` images (one per frame at ``fps``), simulated through, its
    surfaces of ``texture`` (:data:`TEXTURES`); ``held_out_on_orbit``: see :class:`pidg.scenes.capture.Orbit`."""
    check_texture(texture)  # before anything is built
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    rng = np.random.default_rng(seed)
    sim_end = FIRST_IMAGE_FRAME + n_images  # one frame past the last image
    scene.frame_start, scene.frame_end = 1, sim_end
    scene.render.fps = fps
    material = functools.partial(textured_material, texture=texture)
    _common(scene, rng, kind, material)
    dynamic = _BUILDERS[kind](scene, rng, sim_end, material)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.sensor_fit, camera.data.angle_x = "HORIZONTAL", math.radians(FOV_X_DEG)
    camera.data.clip_start, camera.data.clip_end = 0.01, 100.0
    scene.collection.objects.link(camera)
    scene.camera = camera
    static = [o.name for o in scene.objects if o.type == "MESH" and o.name not in {n for n, _ in dynamic}]
    target, radius = ((0.0, 0.0, 0.75), 6.0) if kind == "rigid" else ((0.0, 0.0, 0.55), 5.2)  # rigid: objects drop from 2.3
    orbit = Orbit(target=target, radius=radius, azimuth0_deg=float(rng.uniform(0, 360)), static=static_camera,
                  held_out_on_orbit=held_out_on_orbit)
    bake(scene)
    return BuiltScene(dynamic, static, camera.name, orbit, sim_end, fps)


def _caches(scene: Any) -> list[Any]:
    caches = [scene.rigidbody_world.point_cache] if scene.rigidbody_world is not None else []
    return caches + [m.point_cache for o in scene.objects for m in o.modifiers if hasattr(m, "point_cache")]


def bake(scene: Any) -> None:
    """Bake every physics cache (in memory). Why: an unbaked cache is reset by any later change to the scene (render
    settings, the output path), and re-simulating rigid bodies then gives other trajectories than the ground truth's;
    a baked cache is read-only, so renders and ground truth read the same frames."""
    import bpy

    if not _caches(scene):
        return
    with quiet_fds() as log, bpy.context.temp_override(scene=scene):
        result = bpy.ops.ptcache.bake_all(bake=True)
    unbaked = [c for c in _caches(scene) if not c.is_baked]
    if "FINISHED" not in result or unbaked:
        raise RuntimeError(f"Blender did not bake the simulation ({result}; {' '.join(''.join(log).split())[-300:]})")


# ---- evaluated meshes -------------------------------------------------------------------------------------------------
def set_time(frame: int, subframe: float = 0.0) -> Any:
    """Move the scene to ``frame + subframe`` and return the evaluated depsgraph (physics read from the caches)."""
    import bpy

    bpy.context.scene.frame_set(frame, subframe=subframe)
    return bpy.context.evaluated_depsgraph_get()


def evaluated_mesh(name: str, depsgraph: Any, with_faces: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """World positions [V, 3] float64 of object ``name``'s evaluated mesh (after modifiers and physics) and its
    triangles [F, 3] int64 (``with_faces``)."""
    import bpy

    obj = bpy.data.objects[name].evaluated_get(depsgraph)
    mesh = obj.to_mesh()
    try:
        co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        faces = None
        if with_faces:
            tris = mesh.loop_triangles
            faces = np.empty(3 * len(tris), dtype=np.int32)
            tris.foreach_get("vertices", faces)
            faces = faces.reshape(-1, 3).astype(np.int64)
        matrix = np.array(obj.matrix_world, dtype=np.float64)
    finally:
        obj.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3], faces


# ---- rendering ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RenderSetup:
    engine: str  # "CYCLES", or the fallback used
    samples: int
    denoiser: str | None
    note: str  # what fell back, if anything


def configure_render(width: int, height: int, samples: int, seed: int, denoise: bool = True) -> RenderSetup:
    """Cycles on the CPU at ``samples`` samples a pixel, OpenImageDenoise when the build has it, RGBA PNG with a
    transparent background, the 'Standard' view transform (plain sRGB); Eevee, then Workbench, only when this bpy
    has no Cycles (the setup says so)."""
    import bpy

    scene = bpy.context.scene
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = width, height, 100
    r.film_transparent = True
    r.image_settings.file_format, r.image_settings.color_mode, r.image_settings.color_depth = "PNG", "RGBA", "8"
    r.use_persistent_data = True
    scene.view_settings.view_transform = "Standard"
    note = ""
    for engine in ("CYCLES", "BLENDER_EEVEE", "BLENDER_WORKBENCH"):
        try:
            r.engine = engine
            break
        except TypeError:
            note += f"{engine} is not in this bpy build; "
    if r.engine != "CYCLES":
        return RenderSetup(r.engine, samples, None, note + f"rendering with {r.engine}")
    c = scene.cycles
    c.device, c.samples, c.seed, c.use_animated_seed = "CPU", samples, seed, False
    c.use_adaptive_sampling = True
    c.max_bounces, c.diffuse_bounces, c.glossy_bounces, c.transmission_bounces = 4, 2, 1, 0
    c.caustics_reflective = c.caustics_refractive = False
    denoiser = None
    if denoise:
        try:
            import _cycles

            if getattr(_cycles, "with_openimagedenoise", False):
                c.use_denoising, c.denoiser = True, "OPENIMAGEDENOISE"
                denoiser = "OPENIMAGEDENOISE"
            else:
                note += "no OpenImageDenoise in this build: not denoised; "
        except (ImportError, TypeError) as err:
            note += f"denoising unavailable ({err}); "
    if denoiser is None:
        c.use_denoising = False
    return RenderSetup("CYCLES", samples, denoiser, note.strip("; "))


def _matrix(c2w: np.ndarray) -> Any:
    import mathutils

    return mathutils.Matrix([list(map(float, row)) for row in c2w])


def render_image(camera_name: str, c2w: np.ndarray, path: Path) -> None:
    """Render the current frame from the OpenGL camera-to-world ``c2w`` to ``path`` (RGBA PNG)."""
    import bpy

    bpy.data.objects[camera_name].matrix_world = _matrix(c2w)
    bpy.context.scene.render.filepath = str(path)
    with quiet_fds() as log:
        result = bpy.ops.render.render(write_still=True)
    if "FINISHED" not in result or not path.is_file():
        raise RuntimeError(f"{path}: Blender did not render the frame ({' '.join(''.join(log).split())[-300:]})")


# ---- Blender's own checks of the ground truth ------------------------------------------------------------------------
def camera_agreement(camera_name: str, c2w: np.ndarray, camera: Camera, points: np.ndarray) -> float:
    """Largest distance in pixels between Blender's projection of ``points`` [N, 3] (``world_to_camera_view`` of
    the camera that renders the images) and pidg's ``camera`` built from the json: 0 up to rounding when the two
    camera models agree (points in front of the camera only)."""
    import bpy
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    scene = bpy.context.scene
    cam = bpy.data.objects[camera_name]
    cam.matrix_world = _matrix(c2w)
    bpy.context.view_layer.update()
    ndc = np.array([tuple(world_to_camera_view(scene, cam, Vector(p))) for p in points])
    ours, z = camera.project_points(torch.from_numpy(points))
    ahead = z.numpy() > camera.near
    theirs = np.stack([ndc[:, 0] * camera.width, (1.0 - ndc[:, 1]) * camera.height], axis=-1)
    return float(np.abs(theirs - ours.numpy())[ahead].max()) if ahead.any() else 0.0


def ray_cast_agreement(depsgraph: Any, camera: Camera, depth: np.ndarray, dynamic: np.ndarray,
                       dynamic_names: set[str], stride: int) -> dict[str, Any]:
    """Blender's own ray cast (``Scene.ray_cast`` on the evaluated scene, its BVH) through every ``stride``-th pixel
    centre of ``camera``, compared with the stored depth (camera z, world units) and dynamic mask."""
    import bpy
    from mathutils import Vector

    rot, trans = camera_arrays(camera)
    centre = -rot.T @ trans
    scene = bpy.context.scene
    depth_err, hit_mismatch, dynamic_mismatch, rays = [], 0, 0, 0
    for i in range(stride // 2, camera.height, stride):
        for j in range(stride // 2, camera.width, stride):
            direction = rot.T @ np.array([(j + 0.5 - camera.cx) / camera.fx, (i + 0.5 - camera.cy) / camera.fy, 1.0])
            hit, location, _, _, obj, _ = scene.ray_cast(depsgraph, Vector(centre), Vector(direction / np.linalg.norm(direction)))
            rays += 1
            if hit != (depth[i, j] > 0):
                hit_mismatch += 1
                continue
            if hit:
                z = float((rot @ np.array(location) + trans)[2])
                depth_err.append(abs(z - float(depth[i, j])))
                dynamic_mismatch += (obj.original.name in dynamic_names) != bool(dynamic[i, j])
    return {"rays": rays, "hit_mismatch": hit_mismatch, "dynamic_mismatch": dynamic_mismatch, "depth_abs_error": depth_err}
