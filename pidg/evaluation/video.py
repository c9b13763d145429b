"""MP4 videos of renders (imageio with the ffmpeg binary that the imageio-ffmpeg wheel ships)."""
from __future__ import annotations

import importlib.util
import logging
from pathlib import Path
from typing import Iterable

import numpy as np
from torch import Tensor

from pidg.evaluation.images import to_uint8

logger = logging.getLogger(__name__)
FFMPEG_MISSING = "imageio-ffmpeg is not installed (pip install imageio-ffmpeg)"


def ffmpeg_available() -> bool:
    """Whether imageio can encode MP4: without the imageio-ffmpeg wheel it would hand a .mp4 to another plugin
    (tifffile, where installed) that fails with an unrelated error."""
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def write_video(frames: Iterable[Tensor | np.ndarray], path: Path | str, fps: int = 24) -> Path:
    """Encode [H, W, 3] frames (float in [0, 1] or uint8) as H.264 MP4; falls back to an animated GIF.

    The fallback keeps `pidg render` useful where no ffmpeg is available; the log says which was written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = [f if isinstance(f, np.ndarray) else to_uint8(f) for f in frames]
    if not arrays:
        raise ValueError(f"write_video({path}): no frames")
    import imageio.v2 as imageio

    try:
        if not ffmpeg_available():
            raise ImportError(FFMPEG_MISSING)
        # macro_block_size=1: keep odd sizes as they are instead of silently resizing them
        with imageio.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=1, pixelformat="yuv420p"
                                if all(s % 2 == 0 for s in arrays[0].shape[:2]) else "yuv444p") as writer:
            for frame in arrays:
                writer.append_data(frame)
        return path
    except (ImportError, RuntimeError, OSError) as err:
        gif = path.with_suffix(".gif")
        logger.warning("could not write MP4 (%s); writing %s instead", err, gif)
        imageio.mimsave(gif, arrays, duration=1000.0 / fps, loop=0)
        return gif
