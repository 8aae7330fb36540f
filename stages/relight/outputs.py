"""Write a render sequence frame by frame: linear EXR, sRGB PNG preview, then an MP4.

Each frame is written as soon as it is rendered, so an error mid-sequence keeps every frame
already done; the MP4 is assembled from the PNGs that exist (``finish``), also after an error.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from scene.image_io import write_exr, write_png_srgb
from stages.relight.output import RelightOutput


class SequenceWriter:
    """Sequence ``name`` of a relight output: its frames, previews and video (``RelightOutput``)."""

    def __init__(self, out: RelightOutput, name: str, fps: float, log: logging.Logger,
                 exposure: float | None = None) -> None:
        self.out, self.name, self.fps, self.log = out, name, fps, log
        out.frames_dir(name).mkdir(parents=True, exist_ok=True)
        out.previews_dir(name).mkdir(parents=True, exist_ok=True)
        self.exposure = exposure  # fixed from the first frame so a sequence does not flicker
        self.written: list[Path] = []

    def write(self, index: int, rgb: np.ndarray, alpha: np.ndarray) -> None:
        """Write one frame: RGBA EXR (linear, float16) and an sRGB PNG preview."""
        write_exr(self.out.frame_path(self.name, index), np.concatenate([rgb, alpha[..., None]], -1))
        if self.exposure is None:
            peak = float(np.percentile(rgb[alpha > 0.5], 99)) if (alpha > 0.5).any() else float(rgb.max())
            self.exposure = 0.8 / max(peak, 1e-8)
        png = self.out.preview_path(self.name, index)
        write_png_srgb(png, rgb, exposure=self.exposure)
        self.written.append(png)

    def finish(self) -> Path | None:
        """Assemble the previews into the sequence's video (H.264 via imageio's ffmpeg); None if no frame."""
        if not self.written:
            return None
        import imageio.v2 as imageio

        from scene.image_io import read_png

        path = self.out.video_path(self.name)
        # H.264 wants even sizes; macro_block_size=2 pads at most one pixel.
        with imageio.get_writer(path, fps=self.fps, codec="libx264", quality=8, macro_block_size=2,
                                ffmpeg_log_level="error") as writer:
            for png in self.written:
                writer.append_data(np.round(read_png(png) * 255).astype(np.uint8))
        self.log.info("wrote %s (%d frames)", path, len(self.written))
        return path
