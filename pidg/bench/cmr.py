"""Cost of L_CMR per training step: forward + backward time by sample size and variant, and peak memory by N.

``pidg bench cmr`` prints a table (and ``--out FILE`` writes JSON). Variants, timed interleaved
(the machine is shared and noisy, so only same-run ratios are meaningful):
  * ``tangents``: the material field's hand-written forward-mode tangents (what training uses), in one block of M
    and, if ``block_size`` < M, in blocks;
  * ``tangents+ckpt``: the same in blocks of ``block_size`` with ``checkpoint_blocks`` (activations recomputed in
    backward, so only one block's are alive at a time);
  * ``torch.func``: the same field differentiated by ``jet_from_function`` (four ``torch.func.jvp``).
Peak memory is the RSS growth of one step in a fresh process (torch allocations are invisible to tracemalloc, and
a long-lived process reuses freed memory).
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from pidg.bench.provenance import git_commit, machine, machine_line
from pidg.bench.timing import interleaved_medians, peak_rss_growth_mib
from pidg.device import synchronize
from pidg.models.jet import FieldJet, jet_from_function
from pidg.models.material_field import MaterialField, MaterialFieldConfig
from pidg.models.time_axis import TimeAxis
from pidg.physics import PhysicsConfig, cmr_loss

VARIANTS = ("tangents", "tangents+ckpt", "torch.func")


@dataclass
class CMRBenchConfig:
    samples: tuple[int, ...] = (1024, 2048, 4096)
    particles: tuple[int, ...] = (20_000, 200_000)  # N for the memory comparison (timing uses the first)
    variants: tuple[str, ...] = VARIANTS
    repeats: int = 7
    seed: int = 0
    physics: PhysicsConfig = field(default_factory=lambda: PhysicsConfig(kind="cmr"))
    material: MaterialFieldConfig = field(default_factory=MaterialFieldConfig)
    device: str = "cpu"  # timing runs here; peak memory is measured on the CPU only


class _TorchFuncJet:
    """The field's jet by ``torch.func.jvp`` of its forward: the generic route, for comparison."""

    def __init__(self, field: MaterialField) -> None:
        self.field = field

    def jet(self, x: Tensor, t: float | Tensor, index: Tensor) -> FieldJet:
        return jet_from_function(lambda xx, tt: self.field(xx, tt, index), x, torch.as_tensor(t, dtype=x.dtype))


def _step_fn(
    n: int, physics: PhysicsConfig, material: MaterialFieldConfig, variant: str, seed: int, device: str = "cpu"
) -> Callable[[], None]:
    """One training-step worth of L_CMR: sample, forward, backward into the field and the positions (a leaf
    standing in for the deformation's output, a few particles just outside the field's box)."""
    torch.manual_seed(seed)
    field_ = MaterialField(None, n, material).to(device)
    positions = (torch.rand(n, 3) * 2.2 - 1.1).to(device).requires_grad_(True)
    index = torch.arange(n, device=device)
    dev = torch.device(device)
    if variant == "tangents+ckpt":
        physics = dataclasses.replace(physics, checkpoint_blocks=True)
    source = _TorchFuncJet(field_) if variant == "torch.func" else field_
    generator = torch.Generator().manual_seed(seed)
    params = [*field_.parameters(), positions]
    time_axis = TimeAxis(physics_per_dataset=1.0, frame_interval=1.0)

    def step() -> None:
        cmr_loss(source, positions, 0.37, index, physics, time_axis, generator).loss.backward()
        for p in params:
            p.grad = None
        synchronize(dev)

    return step


def measure_peak_rss(n: int, physics: PhysicsConfig, material: MaterialFieldConfig, variant: str = "tangents", seed: int = 0) -> float:
    """Peak RSS growth (MiB) over one step at N particles, sampled every 0.5 ms in a fresh process."""
    setup = (
        "import dataclasses, json\n"
        "from pidg.bench.cmr import _step_fn\n"
        "from pidg.models.material_field import MaterialFieldConfig\n"
        "from pidg.physics import PhysicsConfig\n"
        f"physics = PhysicsConfig(**json.loads({json.dumps(json.dumps(dataclasses.asdict(physics)))}))\n"
        f"material = MaterialFieldConfig(**json.loads({json.dumps(json.dumps(dataclasses.asdict(material)))}))\n"
        f"_step_fn(64, dataclasses.replace(physics, samples=8, block_size=8), material, '{variant}', 0)()  # load kernels\n"
        f"step = _step_fn({n}, physics, material, '{variant}', {seed})\n"
    )
    return peak_rss_growth_mib(setup, "step()")


def _cases(m: int, block: int, variants: tuple[str, ...]) -> list[tuple[str, int]]:
    """(variant, block size) pairs at sample size M: plain variants in one block, checkpointing in blocks of
    ``block`` (checkpointing a single block saves nothing: its activations are rebuilt all at once)."""
    cases = [(v, m) for v in variants if v != "tangents+ckpt"]
    if block < m:
        cases.append(("tangents", block))
    if "tangents+ckpt" in variants:
        cases.append(("tangents+ckpt", min(block, m)))
    return list(dict.fromkeys(cases))


def bench_cmr(config: CMRBenchConfig | None = None, log: Callable[[str], None] = print) -> dict:
    """Median forward + backward ms per (M, variant, block), and peak MiB per (N, M, variant, block)."""
    config = config or CMRBenchConfig()
    base, mat = config.physics, config.material
    log(machine_line(machine(), git_commit()))
    log(f"device {config.device}, torch threads {torch.get_num_threads()}; width {mat.width}, depth {mat.depth}, activation {mat.activation}, "
        f"planes {mat.spatial_resolution}^2 / {mat.spatial_resolution}x{mat.time_resolution} x {mat.plane_channels}")
    n_time = config.particles[0]
    fns: dict[str, Callable[[], None]] = {}
    for m in config.samples:
        for variant, block in _cases(m, base.block_size, config.variants):
            physics = dataclasses.replace(base, samples=m, block_size=block)
            fns[f"M={m} {variant} block={block}"] = _step_fn(n_time, physics, mat, variant, config.seed, config.device)
    m_default = dataclasses.replace(base, samples=min(config.samples), block_size=min(config.samples))
    for n in config.particles[1:]:  # the same step with more particles: only drawing the subset grows with N
        fns[f"N={n} M={m_default.samples} tangents"] = _step_fn(n, m_default, mat, "tangents", config.seed, config.device)
    medians = interleaved_medians(fns, {name: config.repeats for name in fns})
    timing = {name: 1e3 * s for name, s in medians.items()}
    log(f"forward + backward, N = {n_time} unless stated, median of {config.repeats} interleaved runs:")
    for name, ms in timing.items():
        log(f"  {name:<36}{ms:8.1f} ms")
    memory: dict[str, float] = {}
    if config.device != "cpu":
        return {"timing_ms": timing, "peak_mib": memory}
    log("peak RSS growth of one step (fresh process):")
    for n in config.particles:
        for m in config.samples:
            for variant, block in _cases(m, base.block_size, tuple(v for v in config.variants if v != "torch.func")):
                physics = dataclasses.replace(base, samples=m, block_size=block)
                key = f"N={n} M={m} {variant} block={block}"
                memory[key] = measure_peak_rss(n, physics, mat, variant, config.seed)
                log(f"  {key:<44}{memory[key]:8.1f} MiB")
    return {"timing_ms": timing, "peak_mib": memory}


def run_cmr_bench(config: CMRBenchConfig, out: Path | None = None) -> dict:
    """``pidg bench cmr``: the tables, and JSON with the config and every figure at ``out``."""
    result = bench_cmr(config)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"config": dataclasses.asdict(config), **result}, indent=2))
    return result
