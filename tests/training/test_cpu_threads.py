"""A CPU run's torch thread count (``TrainConfig.cpu_torch_threads``) holds during its steps and no longer."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import dataclasses

import pytest
import torch

from pidg.models import parallel_linear
from pidg.training.trainer import Trainer


@pytest.mark.parametrize("threads", [1, 0])
def test_cpu_steps_run_torch_on_the_configured_threads_and_training_restores_them(small_scene, small_config, tmp_path, threads):
    """``cpu_torch_threads`` holds during every step (0: torch's own count, untouched); train() gives the caller's
    count back when it returns."""
    trainer = Trainer(dataclasses.replace(small_config(tmp_path, 3), cpu_torch_threads=threads), small_scene)
    seen: list[int] = []
    step = trainer.train_step
    trainer.train_step = lambda **kw: (seen.append(torch.get_num_threads()), step(**kw))[1]  # type: ignore[method-assign]
    caller = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        trainer.train()
        assert seen == [threads or 3] * 3 and torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(caller)


@pytest.mark.parametrize(("torch_threads", "matmul", "expected"), [(1, 0, 3), (1, 2, 2), (0, 2, None)])
def test_cpu_steps_run_the_networks_products_on_cpu_matmul_threads(small_scene, small_config, tmp_path, torch_threads, matmul, expected):
    """With torch on ``cpu_torch_threads``, the layers' products run on ``cpu_matmul_threads`` (0: the caller's
    count); with torch's own count (0) nothing switches; after train() no switch is left behind."""
    config = dataclasses.replace(small_config(tmp_path, 2), cpu_torch_threads=torch_threads, cpu_matmul_threads=matmul)
    trainer = Trainer(config, small_scene)
    seen: list[int | None] = []
    step = trainer.train_step
    trainer.train_step = lambda **kw: (seen.append(parallel_linear._threads), step(**kw))[1]  # type: ignore[method-assign]
    caller = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        trainer.train()
        assert seen == [expected] * 2 and parallel_linear._threads is None
    finally:
        torch.set_num_threads(caller)
