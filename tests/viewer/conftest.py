import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import pytest
import torch

from pidg.checkpoint import CONFIG_FILE
from pidg.config_tools import save_config
from pidg.data import DataConfig, load_scene
from pidg.data.procedural import ProceduralSceneConfig, write_procedural_dataset
from pidg.models.deformation import DeformationConfig, Grid4DConfig, HashGridConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.models.material_field import MaterialFieldConfig
from pidg.training.config import TrainConfig

SMALL = DeformationConfig(
    grid4d=Grid4DConfig(spatial_grid=HashGridConfig(4, 2, 12, 4, 64), temporal_grid=HashGridConfig(4, 2, 12, 4, 16), width=16)
)


@pytest.fixture(scope="session")
def viewer_run(tmp_path_factory):
    """A run folder as pidg train leaves it (config.json naming its dataset, checkpoint.pt), without training: a
    model that moves, with a material field and a static/dynamic split, so every view mode has something to show."""
    root = tmp_path_factory.mktemp("viewer")
    data_dir = write_procedural_dataset(
        ProceduralSceneConfig(n_train=6, n_test=2, width=48, height=40, n_gaussians=800, n_init_points=400), root / "data"
    )
    config = TrainConfig(data=DataConfig(path=data_dir, progress=False))
    scene = load_scene(config.data)
    model = DynamicGaussians.from_scene(scene, GaussianModelConfig(), SMALL, MaterialFieldConfig(width=8, embedding_dim=4))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for name, p in model.deformation.named_parameters():
            if name.startswith("head_"):
                p.copy_(torch.randn(p.shape, generator=gen) * 0.05)
        for p in model.material_field.parameters():
            p.add_(torch.randn(p.shape, generator=gen) * 0.1)
    model.set_dynamic_mask(torch.arange(model.num_gaussians) % 2 == 0)
    run = root / "run"
    run.mkdir()
    save_config(config, run / CONFIG_FILE)
    torch.save({"format": "pidg-checkpoint-2", "model": model.state_dict(), "step": 0}, run / "checkpoint.pt")
    return run
