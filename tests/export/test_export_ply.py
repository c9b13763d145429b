"""`pidg export`: the Gaussians at a time in the standard 3DGS PLY layout, read back with an independent reader
(plyfile) following the original 3DGS loader's conventions, rendered, and compared with the model's own render."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import json
import re

import numpy as np
import pytest
import torch

from pidg.cli import main
from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.export import export_ply, export_ply_sequence, sequence_times
from pidg.models.deformation import DeformationConfig, Grid4DConfig, HashGridConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.render import rasterize

plyfile = pytest.importorskip("plyfile", reason="plyfile (the independent PLY reader) is in the test extra: pip install plyfile")

SMALL = DeformationConfig(
    grid4d=Grid4DConfig(spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16)
)
#: The vertex properties of the original 3DGS code's save_ply for SH degree 3, written out here independently.
THREEDGS_PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


@pytest.fixture(scope="module")
def scene():
    return make_procedural_scene(ProceduralSceneConfig(n_train=5, n_test=2, width=40, height=32, n_gaussians=600, n_init_points=300))


def make_run(scene, path, active_sh_degree: int):
    """A run folder holding a model that moves, has view-dependent colour in every SH band (random coefficients,
    also above its active degree: they must not reach the file) and a static/dynamic split."""
    model = DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, None)
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for name, p in model.deformation.named_parameters():
            if name.startswith("head_"):
                p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
        g = model.gaussians.params
        g["sh_rest"].copy_(torch.randn(g["sh_rest"].shape, generator=gen) * 0.3)
        g["opacity_logits"].copy_(torch.randn(g["opacity_logits"].shape, generator=gen))
        g["quats"].mul_(2.5)  # unnormalised, as training leaves them
    model.gaussians.active_sh_degree = active_sh_degree
    model.set_dynamic_mask(torch.arange(model.num_gaussians) % 3 != 0)
    path.mkdir(parents=True, exist_ok=True)
    torch.save({"format": "pidg-checkpoint-2", "model": model.state_dict()}, path / "checkpoint.pt")
    return model


def read_3dgs_ply(path):
    """Gaussians from a PLY the way the original 3DGS loader reads them (plyfile; features_extra reshaped to
    [N, 3, M] and transposed; sigmoid opacity, exp scales, normalised wxyz rotations)."""
    data = plyfile.PlyData.read(str(path))
    v = data["vertex"]
    n = v.count
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
    f_dc = np.stack([v["f_dc_0"], v["f_dc_1"], v["f_dc_2"]], axis=1)
    rest_names = sorted((p.name for p in v.properties if p.name.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    m = len(rest_names) // 3
    f_rest = np.stack([v[name] for name in rest_names], axis=1) if m else np.zeros((n, 0), np.float32)
    f_rest = f_rest.reshape(n, 3, m).transpose(0, 2, 1)
    sh = torch.from_numpy(np.concatenate([f_dc[:, None, :], f_rest], axis=1).astype(np.float32))
    rot = torch.from_numpy(np.stack([v[f"rot_{i}"] for i in range(4)], axis=1).astype(np.float32))
    return {
        "data": data,
        "means": torch.from_numpy(xyz.astype(np.float32)),
        "sh": sh,
        "sh_degree": int(round((m + 1) ** 0.5)) - 1,
        "opacities": torch.sigmoid(torch.from_numpy(np.asarray(v["opacity"], np.float32))),
        "scales": torch.exp(torch.from_numpy(np.stack([v[f"scale_{i}"] for i in range(3)], axis=1).astype(np.float32))),
        "quats": rot / rot.norm(dim=1, keepdim=True),
    }


@pytest.mark.parametrize("active_sh_degree", [1, 3])
def test_exported_ply_renders_like_the_model_at_that_time(scene, tmp_path, active_sh_degree):
    model = make_run(scene, tmp_path / "run", active_sh_degree)
    t = 0.37
    path = export_ply(tmp_path / "run", t, tmp_path / "out" / "t037.ply", device="cpu")
    g = read_3dgs_ply(path)
    data = g["data"]
    assert data.elements[0].name == "vertex" and len(data.elements) == 1
    assert not data.text and data.byte_order == "<"  # binary little-endian
    assert [p.name for p in data["vertex"].properties] == THREEDGS_PROPERTIES
    assert {data["vertex"].data.dtype[name] for name in THREEDGS_PROPERTIES} == {np.dtype("<f4")}
    assert data["vertex"].count == model.num_gaussians
    assert any("t = 0.37" in c for c in data.comments)
    # bands above the run's active degree are zero in the file (the renders below agree only if so)
    rest = g["sh"][:, 1:]
    assert torch.count_nonzero(rest[:, (active_sh_degree + 1) ** 2 - 1 :]) == 0

    with torch.no_grad():
        for frame in (scene.test[0], scene.train[2]):
            expected = model.render(frame.camera, t)
            out = rasterize(g["means"], g["quats"], g["opacities"], g["sh"], frame.camera, scales=g["scales"],
                            background=model.background, sh_degree=g["sh_degree"])
            assert expected.alpha.mean() > 0.05  # the comparison sees the scene
            torch.testing.assert_close(out.rgb, expected.rgb, atol=2e-5, rtol=0)
            torch.testing.assert_close(out.alpha, expected.alpha, atol=2e-5, rtol=0)

        # the file holds the deformed Gaussians: dynamic ones moved, static ones canonical
        dynamic = model.dynamic_mask
        at_t = model.at(t)
        torch.testing.assert_close(g["means"], at_t.means)
        assert torch.equal(g["means"][~dynamic], model.canonical().means[~dynamic])
        assert not torch.allclose(g["means"][dynamic], model.canonical().means[dynamic])
        torch.testing.assert_close(torch.log(g["scales"]), at_t.log_scales, atol=1e-5, rtol=0)


def test_a_sequence_is_one_ply_per_time_with_an_index(scene, tmp_path):
    model = make_run(scene, tmp_path / "run", 1)
    assert sequence_times(model) == [0.0, 0.25, 0.5, 0.75, 1.0]  # 5 training frames: one per frame interval
    paths = export_ply_sequence(tmp_path / "run", None, tmp_path / "seq", device="cpu")
    assert [p.name for p in paths] == [f"frame_{i:04d}.ply" for i in range(5)]
    index = json.loads((tmp_path / "seq" / "frames.json").read_text())
    assert [f["time"] for f in index["frames"]] == [0.0, 0.25, 0.5, 0.75, 1.0] and index["gaussians"] == model.num_gaussians
    first, last = (read_3dgs_ply(p)["means"] for p in (paths[0], paths[-1]))
    with torch.no_grad():
        torch.testing.assert_close(first, model.at(0.0).means)
        torch.testing.assert_close(last, model.at(1.0).means)
    assert not torch.equal(first, last)

    chosen = export_ply_sequence(tmp_path / "run", [0.1, 0.9], tmp_path / "two", device="cpu", sh_degree=0)
    assert len(chosen) == 2 and len(read_3dgs_ply(chosen[0])["sh"][0]) == 1  # degree 0: f_dc only


def test_cli_export_writes_the_file_and_says_where(scene, tmp_path, capsys):
    make_run(scene, tmp_path / "run", 1)
    assert main(["export", str(tmp_path / "run"), "--time", "0.5", "--device", "cpu"]) == 0
    written = tmp_path / "run" / "export" / "gaussians_t0.5000.ply"
    assert written.is_file() and str(written) in capsys.readouterr().out
    assert main(["export", str(tmp_path / "run"), "--times", "0", "1", "--out", str(tmp_path / "seq"), "--device", "cpu"]) == 0
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == ["frame_0000.ply", "frame_0001.ply", "frames.json"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--time", "1.5"], r"--time 1\.5: outside \[0, 1\] \(dataset time"),
        (["--time", "-0.1"], r"--time -0\.1: outside \[0, 1\]"),
        (["--time", "nan"], r"--time nan: outside \[0, 1\]"),
        (["--times", "0", "2"], r"--times value 2: outside \[0, 1\]"),
    ],
)
def test_cli_export_refuses_a_time_outside_the_video_in_one_line(scene, tmp_path, capsys, args, message):
    make_run(scene, tmp_path / "run", 1)
    assert main(["export", str(tmp_path / "run"), *args, "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err), err
    assert not (tmp_path / "run" / "export").exists()


def test_cli_export_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    (tmp_path / "notes").mkdir()
    assert main(["export", str(tmp_path / "notes"), "--time", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{tmp_path / 'notes'}: not a pidg run folder (no checkpoint.pt" in err
    assert main(["export", str(tmp_path / "missing"), "--time", "0.5"]) == 2
    assert "missing: no such folder" in capsys.readouterr().err
