"""The particle-velocity consistency term: known answers, its units, and that it teaches v the particles' motion (the
deformation's velocity it trains against has its known-answer test beside the motion metrics, tests/evaluation)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

import pidg  # noqa: F401  (before torch is used)
from pidg.data import DataConfig, load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.time_axis import TimeAxis
from pidg.physics import particle_step_velocity, particle_velocity, velocity_mismatch
from pidg.training.config import TrainConfig, apply_preset
from pidg.training.losses import StepInputs
from pidg.training.trainer import Trainer


@pytest.mark.parametrize("time_scale", [0.0, 1.0, 7.5])
def test_mismatch_is_per_frame_in_box_half_extents_whatever_the_time_unit(time_scale):
    """The same motion (a particle that moves 0.3 world units per frame against a field that says 0.1) gives the
    same loss in every physics time unit: |0.2| world units per frame over a half-extent of 2 = 0.1."""
    axis = TimeAxis.from_times([i / 10 for i in range(11)], time_scale)
    per_physics_unit = 1.0 / axis.frame_dt  # world units per physics unit of 1 world unit per frame
    moving = torch.tensor([[0.3, 0.0, 0.0]]) * per_physics_unit
    field = torch.tensor([[0.1, 0.0, 0.0]]) * per_physics_unit
    mismatch = velocity_mismatch(field, moving, axis, torch.tensor([2.0, 2.0, 2.0]))
    assert float(mismatch) == pytest.approx(0.1, rel=1e-6)
    # the half-extent is per axis: an error along z is measured in z's half-extent
    along_z = velocity_mismatch(torch.tensor([[0.0, 0.0, 0.4]]) * per_physics_unit, torch.zeros(1, 3), axis,
                                torch.tensor([1.0, 1.0, 4.0]))
    assert float(along_z) == pytest.approx(0.1, rel=1e-6)
    assert float(velocity_mismatch(torch.zeros(0, 3), torch.zeros(0, 3), axis, torch.ones(3))) == 0.0
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        velocity_mismatch(torch.zeros(2, 3), torch.zeros(3, 3), axis, torch.ones(3))


def test_the_term_teaches_v_the_deformation_velocity_and_leaves_the_deformation_alone(tmp_path):
    data_dir = write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=1, width=32, height=32, n_gaussians=800, n_init_points=300), tmp_path / "data"
    )
    cfg = apply_preset(TrainConfig(data=DataConfig(path=data_dir, progress=False)), "cpu")
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=4096, lambda_kinematic=1.0)
    cfg.densify = dataclasses.replace(cfg.densify, start=10_000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=40)
    cfg.output = dataclasses.replace(cfg.output, dir=tmp_path / "run", checkpoint_every=0, progress=False, preview_every=0)
    trainer = Trainer(cfg, load_scene(cfg.data))
    history = [trainer.train_step() for _ in range(40)]  # the deformation learns some motion
    assert all("kinematic" in h and h["kinematic"] >= 0 for h in history)
    term = next(t for t in trainer.loss_terms if t.name == "kinematic")
    model, frame = trainer.model, trainer.scene.train[2]

    def mismatch() -> torch.Tensor:
        state = model.at(frame.time)  # all 300 particles (fewer than the samples): the same rows every call
        loss, _ = term.loss(StepInputs(0, frame, model, state, True), model.render_state(state, frame.camera), None)
        return loss

    before = mismatch()
    assert float(before.detach()) > 1e-4  # the particles move and v does not follow yet
    model.deformation.zero_grad(set_to_none=True)
    model.material_field.zero_grad(set_to_none=True)
    before.backward()  # the target is detached: no gradient reaches the deformation, only the field
    assert all(p.grad is None or not p.grad.any() for p in model.deformation.parameters())
    assert any(p.grad is not None and p.grad.any() for p in model.material_field.parameters())
    dense = [p for name, p in model.material_field.named_parameters() if name != "index_embedding"]  # sparse grads
    optimizer = torch.optim.Adam(dense, lr=3e-3)
    for _ in range(100):
        optimizer.zero_grad()
        mismatch().backward()
        optimizer.step()
    assert float(mismatch().detach()) < 0.5 * float(before.detach())


def _trained_term(tmp_path, **physics):
    """A 20-step run on a small procedural scene with L_kin (``physics`` options on top) and its L_kin term."""
    data_dir = write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=1, width=32, height=32, n_gaussians=800, n_init_points=300), tmp_path / "data"
    )
    cfg = apply_preset(TrainConfig(data=DataConfig(path=data_dir, progress=False)), "cpu")
    cfg.physics = dataclasses.replace(cfg.physics, kind="cmr", samples=4096, lambda_kinematic=1.0, **physics)
    cfg.densify = dataclasses.replace(cfg.densify, start=10_000)
    cfg.optim = dataclasses.replace(cfg.optim, iterations=20)
    cfg.output = dataclasses.replace(cfg.output, dir=tmp_path / "run", checkpoint_every=0, progress=False, preview_every=0)
    trainer = Trainer(cfg, load_scene(cfg.data))
    for _ in range(20):
        trainer.train_step()
    return trainer, next(t for t in trainer.loss_terms if t.name == "kinematic")


def _independent_mismatch(model, t: float, target) -> torch.Tensor:
    """L_kin at dataset time t against ``target`` (world units per dataset time), written out from the model's parts."""
    with torch.no_grad():
        v = model.material_field(model.at(t).means, t, model.gaussians.particle_index)[0]
        return velocity_mismatch(v, target / model.time_axis.physics_per_dataset, model.time_axis,
                                 model.material_field.normalize.half_extent)


def test_forward_target_is_the_move_over_the_next_training_interval(tmp_path):
    """``kinematic_target forward``: v against (x(t + dt) - x(t)) / dt, dt one training-frame interval (what the
    first-order velocity flow x + v dt must match), not the central difference."""
    trainer, term = _trained_term(tmp_path, kinematic_target="forward")
    model, frame = trainer.model, trainer.scene.train[2]
    dt = model.time_axis.frame_interval
    state = model.at(frame.time)
    loss, _ = term.loss(StepInputs(0, frame, model, state, True), model.render_state(state, frame.camera), None)
    with torch.no_grad():
        forward = (model.at(frame.time + dt).means - state.means) / dt
        central = (model.at(frame.time + 0.5 * dt).means - model.at(frame.time - 0.5 * dt).means) / dt
    torch.testing.assert_close(loss.detach(), _independent_mismatch(model, frame.time, forward), rtol=1e-4, atol=1e-7)
    assert not torch.allclose(forward, central, rtol=1e-3, atol=0)  # the two targets differ here


def test_forward_target_at_the_last_frame_is_the_last_interval_inside_the_recording(tmp_path):
    """At the last training frame (t = 1) the next interval is past the recording, where nothing supervises the
    deformation: the forward target is then the move over the interval that ends at t = 1."""
    trainer, term = _trained_term(tmp_path, kinematic_target="forward")
    model = trainer.model
    frame = max(trainer.scene.train, key=lambda f: f.time)
    assert frame.time == pytest.approx(1.0)
    dt = model.time_axis.frame_interval
    state = model.at(frame.time)
    loss, _ = term.loss(StepInputs(0, frame, model, state, True), model.render_state(state, frame.camera), None)
    with torch.no_grad():
        inside = (state.means - model.at(frame.time - dt).means) / dt
        past = (model.at(frame.time + dt).means - state.means) / dt
    torch.testing.assert_close(loss.detach(), _independent_mismatch(model, frame.time, inside), rtol=1e-4, atol=1e-7)
    assert not torch.allclose(inside, past, rtol=1e-3, atol=0)  # the move past the end is another


def test_time_jitter_teaches_v_at_a_time_drawn_between_the_training_frames(tmp_path):
    """``kinematic_time_jitter``: L_kin at the frame's time moved by a uniform draw of up to half a training-frame
    interval either way (jitter 1), the particles deformed to that time: v is taught between the frames too."""
    trainer, term = _trained_term(tmp_path, kinematic_time_jitter=1.0)
    model, frame = trainer.model, trainer.scene.train[2]
    dt = model.time_axis.frame_interval
    state = model.at(frame.time)
    drawn = []
    for _ in range(6):
        replay = torch.Generator()
        replay.set_state(term.generator.get_state())  # all 300 particles are sampled: the offset is the only draw
        t = frame.time + (float(torch.rand((), generator=replay)) - 0.5) * dt
        loss, _ = term.loss(StepInputs(0, frame, model, state, True), model.render_state(state, frame.camera), None)
        with torch.no_grad():
            central = (model.at(t + 0.5 * dt).means - model.at(t - 0.5 * dt).means) / dt
        torch.testing.assert_close(loss.detach(), _independent_mismatch(model, t, central), rtol=1e-4, atol=1e-7)
        drawn.append(t - frame.time)
    assert all(abs(d) <= 0.5 * dt for d in drawn) and max(drawn) - min(drawn) > 0.1 * dt  # drawn, not fixed
    # clamped to the recording: around the first frame (t = 0) no draw falls before it
    first = min(trainer.scene.train, key=lambda f: f.time)
    start = model.at(first.time)
    for _ in range(4):
        replay = torch.Generator()
        replay.set_state(term.generator.get_state())
        t = max(first.time + (float(torch.rand((), generator=replay)) - 0.5) * dt, 0.0)
        loss, _ = term.loss(StepInputs(0, first, model, start, True), model.render_state(start, first.camera), None)
        with torch.no_grad():
            target = model.motion_velocity(t, 0.5 * dt)
        torch.testing.assert_close(loss.detach(), _independent_mismatch(model, t, target), rtol=1e-4, atol=1e-7)


def test_recording_times_teach_each_particle_at_a_time_of_its_own_over_the_whole_recording(tmp_path):
    """``kinematic_times recording``: each sampled particle at its own time drawn uniformly over [0, 1], deformed
    there, against the deformation's central velocity at that time (one-sided at the ends), written out per particle
    from the model's parts; the frame the step renders does not matter."""
    trainer, term = _trained_term(tmp_path, kinematic_times="recording")
    model, frame = trainer.model, trainer.scene.train[2]
    h = 0.5 * model.time_axis.frame_interval
    state = model.at(frame.time)
    replay = torch.Generator()
    replay.set_state(term.generator.get_state())  # all 300 particles are sampled: the times are the only draws
    times = torch.rand(model.num_gaussians, generator=replay, dtype=torch.float64)
    loss, _ = term.loss(StepInputs(0, frame, model, state, True), model.render_state(state, frame.camera), None)
    with torch.no_grad():
        v, target = [], []
        for i, t in enumerate(times.float().tolist()):  # one particle at a time, at float times: another path
            row = torch.tensor([i])
            means = model.at(t, rows=row).means
            v.append(model.material_field(means, t, model.gaussians.particle_index[row])[0])
            t0, t1 = max(t - h, 0.0), min(t + h, 1.0)
            target.append((model.at(t1, rows=row).means - model.at(t0, rows=row).means) / (t1 - t0))
        expected = velocity_mismatch(torch.cat(v), torch.cat(target) / model.time_axis.physics_per_dataset,
                                     model.time_axis, model.material_field.normalize.half_extent)
    torch.testing.assert_close(loss.detach(), expected, rtol=1e-4, atol=1e-7)
    assert float(times.min()) < 0.1 and float(times.max()) > 0.9  # spread over the recording, not around the frame
    with pytest.raises(ValueError, match="kinematic_time_jitter.*kinematic_times frame"):
        dataclasses.replace(trainer.config.physics, kinematic_time_jitter=1.0)


def test_targets_at_a_time_per_particle_match_the_single_time_path(tmp_path):
    """Both targets with a time per particle (``kinematic_times recording``) give each particle what the single-time
    path gives it at its time: the central velocity one-sided near the ends, the forward move over the last interval
    inside the recording where the next one leaves it."""
    trainer, _ = _trained_term(tmp_path)
    model = trainer.model
    dt = model.time_axis.frame_interval
    rows = torch.tensor([0, 5, 17, 40])
    times = torch.tensor([0.0, 0.003, 0.31, 0.995])  # near the start, inside, past the last interval's start
    with torch.no_grad():
        means = model.at(times, rows=rows).means
        central = particle_velocity(model, times, rows)
        forward = particle_step_velocity(model, times, means, rows)
        for i, (t, r) in enumerate(zip(times.tolist(), rows)):
            alone = model.at(t, rows=r[None]).means
            torch.testing.assert_close(central[i:i + 1], particle_velocity(model, t, r[None]), rtol=1e-4, atol=1e-6)
            torch.testing.assert_close(forward[i:i + 1], particle_step_velocity(model, t, alone, r[None]), rtol=1e-4,
                                       atol=1e-6)
        naive = (model.at(0.995 + dt, rows=rows[3:]).means - means[3:]) / model.time_axis.to_physics(dt)
    assert not torch.allclose(forward[3:], naive, rtol=1e-3, atol=0)  # the move past the end is another
