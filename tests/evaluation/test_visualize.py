"""Pictures of the material field show the model's velocity: none on Gaussians the decoupling made static."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import torch

from pidg.data.procedural import ProceduralSceneConfig, make_procedural_scene
from pidg.evaluation.visualize import material_field_images
from pidg.models.deformation import DeformationConfig
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.models.gaussians import GaussianModelConfig
from pidg.models.material_field import MaterialFieldConfig


def test_static_gaussians_show_no_velocity_however_the_field_is_set():
    scene = make_procedural_scene(ProceduralSceneConfig(n_train=4, n_test=1, width=32, height=32, n_gaussians=600, n_init_points=300))
    model = DynamicGaussians.from_scene(
        scene, GaussianModelConfig(), DeformationConfig(kind="identity"), MaterialFieldConfig(width=8, embedding_dim=4)
    )
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in model.material_field.parameters():
            p.add_(torch.randn(p.shape, generator=gen) * 0.3)  # a field with velocity everywhere
    frame = scene.train[1]
    moving = material_field_images(model, frame, dt=1.0)
    assert moving.max_velocity_px > 0.01
    model.set_dynamic_mask(torch.zeros(model.num_gaussians, dtype=torch.bool))  # everything static
    still = material_field_images(model, frame, dt=1.0)
    assert still.max_velocity_px == 0.0
    assert still.max_stress > 0  # the stress picture still shows the field
