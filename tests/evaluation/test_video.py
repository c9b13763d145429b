"""Videos: MP4 through imageio-ffmpeg, and a GIF (with a warning naming the missing wheel) without it."""
import logging

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

import pidg.evaluation.video as video
from pidg.evaluation.video import write_video


def _frames() -> list[torch.Tensor]:
    ramp = torch.linspace(0, 1, 16)
    return [torch.stack([ramp.expand(12, 16) * k / 3, torch.zeros(12, 16), torch.ones(12, 16) * 0.5], dim=-1) for k in range(4)]


def test_mp4_holds_every_frame(tmp_path):
    if not video.ffmpeg_available():
        pytest.skip("imageio-ffmpeg is not installed")
    path = write_video(_frames(), tmp_path / "v.mp4", fps=4)
    assert path.suffix == ".mp4"
    frames = imageio.mimread(path)
    assert len(frames) == 4 and frames[0].shape == (12, 16, 3)


def test_without_ffmpeg_a_gif_is_written_and_the_log_names_the_wheel(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(video, "ffmpeg_available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="pidg.evaluation.video"):
        path = write_video(_frames(), tmp_path / "v.mp4", fps=4)
    assert path == tmp_path / "v.gif" and not (tmp_path / "v.mp4").exists()
    frames = imageio.mimread(path)
    assert len(frames) == 4 and frames[3].shape[:2] == (12, 16)
    assert np.abs(frames[3][..., 2].astype(int) - 128).max() <= 2  # the blue channel's 0.5, as written
    assert "pip install imageio-ffmpeg" in caplog.text
