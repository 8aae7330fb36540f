"""Write a render sequence frame by frame: linear EXR, sRGB PNG preview, then an MP4.

Each frame is written as soon as it is rendered, so an error mid-sequence keeps every frame
already done; the MP4 is assembled from the PNGs that exist (``finish``), also after an error.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from scene.image_io import write_exr, write_png_srgb


class SequenceWriter:
    """``<folder>/frames/<i:06d>.exr``, ``<folder>/previews/<i:06d>.png``, ``<folder>/<name>.mp4``."""

    def __init__(self, folder: Path, name: str, fps: float, log: logging.Logger, exposure: float | None = None) -> None:
        self.folder, self.name, self.fps, self.log = Path(folder), name, fps, log
        (self.folder / "frames").mkdir(parents=True, exist_ok=True)
        (self.folder / "previews").mkdir(parents=True, exist_ok=True)
        self.exposure = exposure  # fixed from the first frame so a sequence does not flicker
        self.written: list[Path] = []

    def write(self, index: int, rgb: np.ndarray, alpha: np.ndarray) -> None:
        """Write one frame: RGBA EXR (linear, float16) and an sRGB PNG preview."""
        write_exr(self.folder / "frames" / f"{index:06d}.exr", np.concatenate([rgb, alpha[..., None]], -1))
        if self.exposure is None:
            peak = float(np.percentile(rgb[alpha > 0.5], 99)) if (alpha > 0.5).any() else float(rgb.max())
            self.exposure = 0.8 / max(peak, 1e-8)
        png = self.folder / "previews" / f"{index:06d}.png"
        write_png_srgb(png, rgb, exposure=self.exposure)
        self.written.append(png)

    def finish(self) -> Path | None:
        """Assemble the previews into ``<name>.mp4`` (H.264 via imageio's ffmpeg); None if no frame."""
        if not self.written:
            return None
        import imageio.v2 as imageio

        from scene.image_io import read_png

        path = self.folder / f"{self.name}.mp4"
        # H.264 wants even sizes; macro_block_size=2 pads at most one pixel.
        with imageio.get_writer(path, fps=self.fps, codec="libx264", quality=8, macro_block_size=2,
                                ffmpeg_log_level="error") as writer:
            for png in self.written:
                writer.append_data(np.round(read_png(png) * 255).astype(np.uint8))
        self.log.info("wrote %s (%d frames)", path, len(self.written))
        return path
