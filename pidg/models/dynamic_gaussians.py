"""The scene model: what a trained dynamic scene is, and all that any tool needs from it.

``DynamicGaussians`` = canonical Gaussians (``GaussianModel``, with the particle index and, after decoupling, the
static/dynamic split as per-Gaussian rows) + a deformation field + an optional material field + the scene's time
axis and background. Evaluation, renders, pictures, benchmarks, a viewer or an exporter take one of these; the
Trainer holds one and adds only optimisation. ``DynamicGaussians.from_run(RUN)`` reads the model out of a run's
checkpoint and builds nothing else: no optimizer, no densification state, no kNN initialisation, no optical flow.

Units: positions in world units, dataset time t in [0, 1], velocities in world units per physics time unit
(``time_axis``; by default one training-frame interval).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from pidg.checkpoint import CHECKPOINT_FILE, load_checkpoint
from pidg.config_tools import from_jsonable, to_jsonable
from pidg.data.scene import SceneData
from pidg.models.deformation import Bounds, DeformationConfig, DeformationModel, DeformedGaussians, build_deformation
from pidg.models.gaussians import GaussianModel, GaussianModelConfig
from pidg.models.material_field import MaterialField, MaterialFieldConfig
from pidg.models.time_axis import TimeAxis
from pidg.render import Camera, PreparedRender, RenderBackend, RenderOutput, composite, prepare_render

MODEL_FORMAT = "pidg-model-1"
DYNAMIC_MASK = "is_dynamic"  # per-Gaussian bool buffer, present once static/dynamic decoupling has run


class DynamicGaussians:
    """Canonical Gaussians + deformation + optional material field: Gaussians, renders and velocities at any time."""

    def __init__(
        self,
        gaussians: GaussianModel,
        deformation: DeformationModel,
        material_field: MaterialField | None,
        time_axis: TimeAxis,
        background: Tensor,
        backend: RenderBackend = "auto",
    ) -> None:
        self.gaussians = gaussians
        self.deformation = deformation
        self.material_field = material_field
        self.time_axis = time_axis
        self.background = background.to(torch.float32)  # [3] RGB in [0, 1] behind the Gaussians
        self.backend: RenderBackend = backend

    # ---- construction ------------------------------------------------------------------------------------------
    @classmethod
    def from_scene(
        cls,
        scene: SceneData,
        gaussians: GaussianModelConfig,
        deformation: DeformationConfig,
        material: MaterialFieldConfig | None,
        time_scale: float = 0.0,
        backend: RenderBackend = "auto",
    ) -> "DynamicGaussians":
        """A fresh model for a scene: Gaussians from its point cloud (or random), a deformation, and a material
        field when ``material`` is given; ``time_scale`` as ``PhysicsConfig.time_scale``."""
        model = GaussianModel.from_scene(scene, gaussians)
        # Normalise deformation inputs by the box of the initial Gaussians, not the camera sphere: for D-NeRF-like
        # captures the sphere is ~3x the object, which wastes grid resolution and scales the warp 3x
        # (measured on bouncingballs at 200 px, 400 steps: 14 dB with the sphere, 22 dB with the box).
        bounds = Bounds.from_points(model.params["means"].detach())
        warp = build_deformation(deformation, bounds)
        # the material field works in the deformation's box and on the same time axis t in [0, 1]
        field = MaterialField(bounds, model.num_particles, material) if material is not None else None
        time_axis = TimeAxis.from_times((f.time for f in scene.train), time_scale)
        return cls(model, warp, field, time_axis, scene.background, backend)

    @classmethod
    def from_run(cls, run_dir: Path | str, device: torch.device | str | None = None) -> "DynamicGaussians":
        """The model of a finished (or interrupted) run, read from ``RUN/checkpoint.pt``."""
        path = Path(run_dir) / CHECKPOINT_FILE
        model = cls.from_checkpoint(load_checkpoint(path), path)
        return model.to(device) if device is not None else model

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], path: Path | str) -> "DynamicGaussians":
        """The model inside a loaded checkpoint (``path`` names it in errors)."""
        model_state = state.get("model")
        if not isinstance(model_state, dict) or model_state.get("format") != MODEL_FORMAT:
            raise RuntimeError(
                f"{path}: no pidg scene model in it (checkpoint format {state.get('format')!r}); checkpoints of "
                "pidg 0.1 (format pidg-checkpoint-1) are read by that version only"
            )
        return cls.from_state_dict(model_state)

    # ---- sizes and device --------------------------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    @property
    def device(self) -> torch.device:
        return self.gaussians.device

    def to(self, device: torch.device | str) -> "DynamicGaussians":
        """Move every tensor in place (the Gaussians get new Parameter objects: build optimizers after this)."""
        self.gaussians.to(device)
        self.deformation.to(device)
        if self.material_field is not None:
            self.material_field.to(device)
        self.background = self.background.to(device)
        return self

    # ---- static / dynamic split ----------------------------------------------------------------------------------
    @property
    def dynamic_mask(self) -> Tensor | None:
        """[N] bool, True for Gaussians the deformation moves; None before decoupling (all of them move)."""
        return self.gaussians.buffers.get(DYNAMIC_MASK)

    def set_dynamic_mask(self, dynamic: Tensor, static_state: DeformedGaussians | None = None) -> None:
        """Install the static/dynamic split (a per-Gaussian row: densification and checkpoints carry it).

        ``static_state`` (all Gaussians; e.g. their time-averaged deformed state) becomes the canonical position,
        orientation and scale of the static ones, which the deformation no longer moves: without it they would fall
        back to canonical values no training view saw them at."""
        dynamic = dynamic.to(device=self.device, dtype=torch.bool)
        if static_state is not None:
            static = ~dynamic
            p = self.gaussians.params
            with torch.no_grad():
                for name, value in (("means", static_state.means), ("quats", static_state.quats), ("log_scales", static_state.log_scales)):
                    p[name][static] = value[static].to(p[name].dtype)
        if DYNAMIC_MASK in self.gaussians.buffers:
            del self.gaussians.buffers[DYNAMIC_MASK]
        self.gaussians.add_buffer(DYNAMIC_MASK, dynamic)

    # ---- Gaussians at a time -------------------------------------------------------------------------------------
    def canonical(self) -> DeformedGaussians:
        """The canonical Gaussians, undeformed."""
        p = self.gaussians.params
        return DeformedGaussians(p["means"], p["quats"], p["log_scales"])

    def at(
        self, t: float | Tensor, regularize: bool = False, rows: Tensor | None = None, reuse: DeformedGaussians | None = None
    ) -> DeformedGaussians:
        """Means, quaternions and log-scales at dataset time ``t`` (static Gaussians stay canonical once decoupled);
        with ``regularize``, also the deformation's regulariser for this pass (training). ``rows`` [M] (indices):
        only those Gaussians, in that order (a loss that needs a few of them pays for a few). ``reuse``: the same
        Gaussians (those rows, in that order) at another time, from this step's parameters: the deformation takes
        its time-independent features from it instead of computing them again (``DeformedGaussians.invariant``)."""
        p = self.gaussians.params
        means, quats, log_scales = p["means"], p["quats"], p["log_scales"]
        dynamic = self.dynamic_mask
        static = None if dynamic is None else ~dynamic
        if rows is not None:
            means, quats, log_scales = (x.index_select(0, rows) for x in (means, quats, log_scales))
            static = None if static is None else static.index_select(0, rows)
        invariant = None if reuse is None else reuse.invariant
        return self.deformation(means, quats, log_scales, t, static_mask=static, regularize=regularize, invariant=invariant)

    def motion_velocity(self, t: float | Tensor, h: float, rows: Tensor | None = None) -> Tensor:
        """The deformation's own velocity dx/dt [N, 3] at dataset time ``t`` (a float, or [N]: a time per row), in
        world units per unit of dataset time: the central difference of the means over t +- h, one-sided where that
        leaves [0, 1]. ``rows`` as :meth:`at`'s. The motion metrics and the particle-velocity loss both read it."""
        if not h > 0:
            raise ValueError(f"motion_velocity: the step h must be > 0, got {h}")
        if isinstance(t, Tensor):
            t0, t1 = (t - h).clamp_min(0.0), (t + h).clamp_max(1.0)
            span: float | Tensor = (t1 - t0).reshape(-1, 1)
        else:
            t0, t1 = max(t - h, 0.0), min(t + h, 1.0)
            span = t1 - t0
        start = self.at(t0, rows=rows)
        return (self.at(t1, rows=rows, reuse=start).means - start.means) / span

    # ---- rendering -------------------------------------------------------------------------------------------
    def render(self, camera: Camera, t: float, features: Tensor | None = None, sh_degree: int | None = None) -> RenderOutput:
        """The scene at dataset time ``t`` seen from ``camera``; ``features`` [N, C]: extra per-Gaussian channels."""
        return self.render_state(self.at(t), camera, features, sh_degree)

    def render_state(
        self, state: DeformedGaussians, camera: Camera, features: Tensor | None = None, sh_degree: int | None = None,
        feature_pixels: Tensor | None = None,
    ) -> RenderOutput:
        """Render Gaussians already placed at some time (``at`` or ``canonical``) with this model's colours,
        opacities and background (SH degree: the active one unless given); ``feature_pixels`` as ``rasterize``'s."""
        return composite(self.prepare_render(state, camera, sh_degree), features, feature_pixels)

    def prepare_render(self, state: DeformedGaussians, camera: Camera, sh_degree: int | None = None) -> PreparedRender:
        """:meth:`render_state`'s first stage (``pidg.render.api.prepare_render``): the Gaussians projected and
        coloured in ``camera``, for a loss that asks which of them reach some pixels before the features are made;
        ``pidg.render.api.composite`` finishes it."""
        g = self.gaussians
        return prepare_render(
            state.means, state.quats, g.opacities, g.sh, camera, log_scales=state.log_scales, background=self.background,
            sh_degree=g.active_sh_degree if sh_degree is None else sh_degree, backend=self.backend,
        )

    # ---- material field --------------------------------------------------------------------------------------
    def _field(self) -> MaterialField:
        if self.material_field is None:
            raise ValueError("this model has no material field (it was trained with --physics none --flow none)")
        return self.material_field

    def field_values(self, means: Tensor, t: float | Tensor) -> tuple[Tensor, Tensor]:
        """Velocity v [N, 3] (world units per physics time unit) and stress sigma [N, 6] (xx, yy, zz, xy, xz, yz)
        of the material field at positions ``means`` [N, 3] of these Gaussians at dataset time ``t``."""
        return self._field()(means, t, self.gaussians.particle_index)

    def velocities(self, t: float | Tensor, means: Tensor | None = None, rows: Tensor | None = None) -> Tensor:
        """v [N, 3] in world units per physics time unit at dataset time ``t`` (a float, or [N]: one per row), at the
        Gaussians' positions then (``means``, or ``at(t)``'s); zero for static Gaussians once decoupled (they do not
        move, and evaluating the field only where it matters keeps the step cheap). ``rows`` [M]: only those Gaussians
        (``means`` is then theirs)."""
        field = self._field()
        means = self.at(t, rows=rows).means if means is None else means
        index = self.gaussians.particle_index
        dynamic = self.dynamic_mask
        if rows is not None:
            index = index.index_select(0, rows)
            dynamic = None if dynamic is None else dynamic.index_select(0, rows)
        moving = None if dynamic is None else dynamic.nonzero().squeeze(1)
        if moving is None or moving.shape[0] == means.shape[0]:  # every row is dynamic: no gather, no scatter
            return field(means, t, index)[0]
        v = means.new_zeros(means.shape)
        if moving.shape[0]:
            times = t.reshape(-1).index_select(0, moving) if isinstance(t, Tensor) and t.numel() > 1 else t
            v = v.index_copy(0, moving, field(means.index_select(0, moving), times, index.index_select(0, moving))[0])
        return v

    # ---- persistence -----------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything that defines the model, sizes included (``torch.save``-able, device-independent on load)."""
        field = self.material_field
        return {
            "format": MODEL_FORMAT,
            "gaussians": self.gaussians.state_dict(),
            "deformation_config": to_jsonable(DeformationConfig.of(self.deformation)),
            "deformation": self.deformation.state_dict(),
            "material_config": None if field is None else to_jsonable(field.config),
            "material_field": None if field is None else field.state_dict(),
            "time_axis": self.time_axis.state_dict(),
            "background": self.background.tolist(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` into this model (same sizes; the number of Gaussians may differ)."""
        self.gaussians.load_state_dict(state["gaussians"])
        self.deformation.load_state_dict(state["deformation"])
        if (self.material_field is None) != (state["material_field"] is None):
            raise RuntimeError("the saved model and this one disagree on having a material field (physics or flow on)")
        if self.material_field is not None:
            self.material_field.load_state_dict(state["material_field"])
        self.time_axis = TimeAxis.from_state_dict(state["time_axis"])
        self.background = torch.tensor(state["background"], dtype=torch.float32, device=self.device)

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> "DynamicGaussians":
        """A model of the saved sizes with the saved values, on the CPU."""
        gaussians = GaussianModel.from_state_dict(state["gaussians"])
        deformation = build_deformation(from_jsonable(DeformationConfig, state["deformation_config"]), Bounds())
        deformation.load_state_dict(state["deformation"])
        field = None
        if state["material_field"] is not None:
            field = MaterialField(Bounds(), gaussians.num_particles, from_jsonable(MaterialFieldConfig, state["material_config"]))
            field.load_state_dict(state["material_field"])
        return cls(gaussians, deformation, field, TimeAxis.from_state_dict(state["time_axis"]), torch.tensor(state["background"]))
