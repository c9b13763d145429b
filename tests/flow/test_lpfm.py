"""The LPFM loss: values in pixels, valid-pixel averaging, explicit [H, W, 2] shapes on a non-square image."""
from __future__ import annotations

import pytest
import torch

import pidg  # noqa: F401
from pidg.flow.config import FlowConfig
from pidg.flow.decomposition import FlowTarget
from pidg.flow.lpfm import end_point_error, lpfm_loss

H, W = 5, 7  # non-square: a [2, H, W] / [H, W, 2] mix-up cannot pass the shape checks


def setup(valid_rows: slice = slice(0, 3)) -> tuple[FlowTarget, torch.Tensor]:
    gt = torch.zeros(H, W, 2)
    gt[..., 0] = torch.arange(W, dtype=torch.float32)  # varies along x only: transposes would show
    gt[..., 1] = -2.0
    valid = torch.zeros(H, W, dtype=torch.bool)
    valid[valid_rows] = True
    return FlowTarget(gt * valid.unsqueeze(-1), valid), torch.ones(H, W)


def test_loss_is_weighted_l1_in_pixels_over_valid_pixels():
    target, alpha = setup()
    config = FlowConfig(lambda_gaussian=0.5, lambda_velocity=0.25)
    offset_g = torch.tensor([1.0, -2.0])  # |dx| + |dy| = 3 per pixel, EPE sqrt(5)
    offset_v = torch.tensor([0.0, 4.0])
    flow_g = (target.flow + offset_g).requires_grad_(True)
    flow_v = (target.flow + offset_v).requires_grad_(True)
    flow_g_far = flow_g.detach().clone()
    flow_g_far[~target.valid] = 1e6  # unsupervised pixels do not count, whatever they hold
    result = lpfm_loss(flow_g, flow_v, target, alpha, config)
    assert result.loss.item() == pytest.approx(0.5 * 3.0 + 0.25 * 4.0)
    assert result.epe_gaussian == pytest.approx(5**0.5) and result.epe_velocity == pytest.approx(4.0)
    assert result.valid_pixels == 3 * W
    assert lpfm_loss(flow_g_far, flow_v, target, alpha, config).loss.item() == pytest.approx(result.loss.item())
    result.loss.backward()
    assert flow_g.grad is not None and flow_v.grad is not None
    assert (flow_g.grad[~target.valid] == 0).all()
    # d/dflow of mean |.|: sign / (number of valid pixels), no clamping anywhere
    torch.testing.assert_close(flow_g.grad[target.valid], (0.5 * torch.sign(offset_g) / (3 * W)).expand(3 * W, 2))
    assert set(result.scalars()) >= {"lpfm", "epe_gaussian", "epe_velocity", "valid_pixels"}


def test_large_flows_are_not_clamped():
    target, alpha = setup()
    result = lpfm_loss(target.flow + 50.0, None, target, alpha, FlowConfig(lambda_gaussian=1.0))
    assert result.loss.item() == pytest.approx(100.0)
    assert result.epe_velocity is None


def test_low_alpha_pixels_are_excluded():
    target, alpha = setup()
    alpha[0] = 0.01
    config = FlowConfig(min_alpha=0.05)
    flow_g = target.flow.clone()
    flow_g[0] += 10.0  # wrong, but where nothing was rendered
    result = lpfm_loss(flow_g, None, target, alpha, config)
    assert result.loss.item() == 0.0 and result.valid_pixels == 2 * W


def test_no_valid_pixel_gives_a_connected_zero():
    target, alpha = setup(valid_rows=slice(0, 0))
    flow_g = torch.ones(H, W, 2, requires_grad=True)
    result = lpfm_loss(flow_g, flow_g, target, alpha, FlowConfig())
    assert result.loss.item() == 0.0 and result.valid_pixels == 0 and result.epe_gaussian == 0.0
    result.loss.backward()
    assert flow_g.grad is not None and (flow_g.grad == 0).all()


def test_channel_first_flows_are_rejected():
    target, alpha = setup()
    with pytest.raises(ValueError, match=r"flow_gaussian must be \[H, W, 2\]"):
        lpfm_loss(target.flow.permute(2, 0, 1), None, target, alpha, FlowConfig())
    with pytest.raises(ValueError, match="flow_velocity"):
        lpfm_loss(target.flow, target.flow.transpose(0, 1), target, alpha, FlowConfig())
    with pytest.raises(ValueError, match="alpha"):
        lpfm_loss(target.flow, None, target, alpha.T, FlowConfig())
    with pytest.raises(ValueError, match="flow_gt"):
        lpfm_loss(target.flow, None, FlowTarget(target.flow.permute(2, 0, 1), target.valid), alpha, FlowConfig())


def test_end_point_error():
    gt = torch.zeros(H, W, 2)
    flow = torch.zeros(H, W, 2)
    flow[..., 0], flow[..., 1] = 3.0, 4.0
    assert end_point_error(flow, gt).item() == pytest.approx(5.0)
    valid = torch.zeros(H, W, dtype=torch.bool)
    flow[0, 0] = 0.0
    valid[0, 0] = True
    assert end_point_error(flow, gt, valid).item() == 0.0
    assert end_point_error(flow, gt, torch.zeros(H, W, dtype=torch.bool)).item() == 0.0
    with pytest.raises(ValueError):
        end_point_error(flow.permute(2, 0, 1), gt)


def test_depth_change_error_is_added_in_pixel_equivalents_over_known_pixels():
    target, alpha = setup()  # rows 0-2 supervised
    scale = torch.zeros(H, W)
    scale[1:] = 50.0  # depth change known on rows 1-4 (px per world unit): rows 1-2 of the supervised ones
    change = torch.full((H, W), 5.0) * (scale > 0)  # 0.1 world units towards the far side, in px
    target = FlowTarget(target.flow, target.valid, change, scale)
    config = FlowConfig(lambda_gaussian=0.5, lambda_velocity=0.25, lambda_depth_change=2.0)
    dz_g = torch.full((H, W), 0.1, requires_grad=True)  # right
    dz_v = torch.full((H, W), 0.04, requires_grad=True)  # 0.06 world units short: 3 px-equivalents
    result = lpfm_loss(target.flow, target.flow, target, alpha, config, (dz_g, dz_v))
    assert result.loss.item() == pytest.approx(2.0 * 0.25 * 3.0)
    assert result.depth_change_error == pytest.approx(3.0) and "depth_change_error" in result.scalars()
    result.loss.backward()
    assert dz_v.grad is not None and (dz_v.grad[0] == 0).all() and (dz_v.grad[3:] == 0).all()  # unknown / unsupervised
    torch.testing.assert_close(dz_v.grad[1:3], torch.full((2, W), -2.0 * 0.25 * 50.0 / (2 * W)))
    # off by default (the paper's loss), and ignored when the target carries no depth change
    plain = lpfm_loss(target.flow, target.flow, target, alpha, FlowConfig(), (dz_g, dz_v))
    assert plain.loss.item() == 0.0 and plain.depth_change_error is None
    assert lpfm_loss(target.flow, target.flow, setup()[0], alpha, config, (dz_g, dz_v)).depth_change_error is None


def test_depth_change_needs_the_motion_target():
    with pytest.raises(ValueError, match="lambda_depth_change 1.0 needs --flow.target motion"):
        FlowConfig(lambda_depth_change=1.0, target="total")


def test_sample_tiles_keeps_a_band_of_the_occupied_tiles_each_equally_often():
    """A fraction of the 16x16 tiles that hold valid pixels: that many tiles, consecutive in row-major order
    (wrapping), pixels inside them untouched and outside cleared; over many draws every occupied tile is kept about
    ``fraction`` of the time (the sampled loss is an unbiased sample of the full one per pixel)."""
    from pidg.flow import sample_tiles

    gen = torch.Generator().manual_seed(0)
    valid = torch.rand(70, 100, generator=gen) > 0.3  # 5 x 7 tiles, partial ones at the right and bottom
    valid[:16, :] = False  # the first tile row holds nothing
    occupied = [(ty, tx) for ty in range(5) for tx in range(7) if valid[16 * ty:16 * ty + 16, 16 * tx:16 * tx + 16].any()]
    assert len(occupied) == 28
    counts = torch.zeros(5, 7)
    draws = 2000
    for _ in range(draws):
        kept = sample_tiles(valid, 0.25, gen)
        assert not (kept & ~valid).any()
        tiles = [(ty, tx) for ty, tx in occupied if kept[16 * ty:16 * ty + 16, 16 * tx:16 * tx + 16].any()]
        assert len(tiles) == 7  # round(0.25 * 28)
        first = next(i for i in range(28) if occupied[i] in tiles and occupied[i - 1] not in tiles)  # the band's start
        wrapped = [occupied[(first + k) % 28] for k in range(7)]
        assert sorted(tiles) == sorted(wrapped)  # one band of consecutive occupied tiles
        for ty, tx in tiles:  # whole tiles: every valid pixel of a kept tile is kept
            block = (slice(16 * ty, 16 * ty + 16), slice(16 * tx, 16 * tx + 16))
            assert torch.equal(kept[block], valid[block])
            counts[ty, tx] += 1
    share = torch.stack([counts[ty, tx] for ty, tx in occupied]) / draws
    assert (share - 0.25).abs().max() < 0.05
    assert sample_tiles(valid, 1.0, gen) is valid
    assert not sample_tiles(torch.zeros(20, 20, dtype=torch.bool), 0.5, gen).any()
    with pytest.raises(ValueError, match=r"fraction must be in \(0, 1\]"):
        sample_tiles(valid, 0.0, gen)


@pytest.mark.parametrize("channels", [6, 8, 10])
def test_the_loss_at_its_supervised_pixels_equals_the_loss_on_the_whole_image(channels):
    """The training term decodes and scores only the target's valid pixels (supervised_flow_loss): the same loss,
    diagnostics and gradients as decoding the whole render."""
    from pidg.flow.gaussian_flow import decode_depth_changes, decode_flows, decode_flows_at
    from pidg.flow.model_flow import supervised_flow_loss

    g = torch.Generator().manual_seed(3)
    features = (torch.randn(H, W, channels, generator=g) * 3).requires_grad_(True)
    alpha = torch.rand(H, W, generator=g) * 0.9 + 0.02  # some under min_alpha
    valid = torch.rand(H, W, generator=g) > 0.4
    depth = channels == 10
    target = FlowTarget(torch.randn(H, W, 2, generator=g) * 4 * valid.unsqueeze(-1), valid,
                        torch.randn(H, W, generator=g) if depth else None, (torch.rand(H, W, generator=g) > 0.3).float() * 5 if depth else None)
    config = FlowConfig(lambda_gaussian=0.5, lambda_velocity=0.5, lambda_depth_change=1.0 if depth else 0.0, min_alpha=0.05)

    flow_g, flow_v, _ = decode_flows(features, alpha)
    dense = lpfm_loss(flow_g, flow_v, target, alpha, config, decode_depth_changes(features, alpha) if depth else None)
    (dense_grad,) = torch.autograd.grad(dense.loss, features)
    sparse = supervised_flow_loss(features, alpha, target, config)
    (sparse_grad,) = torch.autograd.grad(sparse.loss, features)

    assert sparse.loss.item() == pytest.approx(dense.loss.item(), rel=1e-6) and dense.loss.item() > 0
    assert sparse.scalars() == pytest.approx(dense.scalars(), rel=1e-6)
    assert torch.allclose(sparse_grad, dense_grad, atol=1e-7) and dense_grad.abs().sum() > 0
    with pytest.raises(ValueError, match="share their leading shape"):
        decode_flows_at(features[valid], alpha[valid][:-1], torch.zeros(int(valid.sum()), 2))


@pytest.mark.parametrize("channels", [6, 8])
@pytest.mark.parametrize("min_alpha", [0.05, 0.0])
def test_the_fused_flow_loss_kernel_matches_the_torch_functions(channels, min_alpha):
    """supervised_flow_loss's numba pass (lpfm_cpu) against its torch form: loss, diagnostics and the gradients of
    the channels and of alpha, with pixels under either alpha threshold, flows exactly on target (|x|' = 0 there),
    unequal weights; and a graph-connected zero where no pixel is supervised."""
    from pidg.flow.gaussian_flow import DECODE_MIN_ALPHA
    from pidg.flow.model_flow import supervised_flow_loss

    g = torch.Generator().manual_seed(11)
    features = torch.randn(H, W, channels, generator=g) * 3
    alpha = torch.rand(H, W, generator=g) * 0.9 + 0.02
    alpha[0, :6] = torch.tensor([DECODE_MIN_ALPHA / 2, DECODE_MIN_ALPHA, 0.05, 0.0501, 1.0, 0.3])
    valid = torch.rand(H, W, generator=g) > 0.3
    valid[0, :6] = True
    gt = torch.randn(H, W, 2, generator=g) * 4
    features[1, 0] = 0.0  # pixel (0, 1): flow (0, 0) at any alpha
    gt[1, 0] = 0.0
    valid[1, 0] = True
    target = FlowTarget(gt * valid.unsqueeze(-1), valid)
    config = FlowConfig(lambda_gaussian=0.3, lambda_velocity=0.9, min_alpha=min_alpha)
    results = []
    for kernel in (False, True):
        f, a = features.clone().requires_grad_(True), alpha.clone().requires_grad_(True)
        result = supervised_flow_loss(f, a, target, config, kernel=kernel)
        result.loss.backward()
        results.append((result, f.grad, a.grad))
    (ref, ref_f, ref_a), (fused, fused_f, fused_a) = results
    assert fused.loss.dtype == torch.float32 and fused.loss.item() == pytest.approx(ref.loss.item(), rel=1e-6)
    assert fused.scalars() == pytest.approx(ref.scalars(), rel=1e-5)
    torch.testing.assert_close(fused_f, ref_f, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(fused_a, ref_a, rtol=1e-5, atol=1e-6)
    assert ref_a.abs().sum() > 0 and ref_f[..., 4].abs().sum() > 0
    none = FlowTarget(gt, torch.zeros(H, W, dtype=torch.bool))
    f = features.clone().requires_grad_(True)
    empty = supervised_flow_loss(f, alpha, none, config, kernel=True)
    empty.loss.backward()
    assert empty.loss.item() == 0.0 and empty.valid_pixels == 0 and f.grad.abs().sum() == 0
    with pytest.raises(ValueError, match=r"takes \[K, 6 or 8\] channels \(none for depth changes\), got \[\d+, 10\]"):
        supervised_flow_loss(torch.zeros(H, W, 10), alpha, target, config, kernel=True)
