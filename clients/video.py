"""Episode videos: MP4 through imageio-ffmpeg (the `video` extra), else an animated GIF through Pillow."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


class VideoWriter:
    """Appends RGB frames to `path` as they come (MP4), or buffers them for a GIF when ffmpeg is missing.

    Attributes:
        path: The file written: `path` itself, or `path` with a .gif suffix after the fallback.
    """

    def __init__(self, path: Path, fps: float, strip_every: int = 0) -> None:
        self.fps = fps
        self.strip_every = strip_every
        self._strip: list[tuple[np.ndarray, str]] = []
        self._count = 0
        self._frames: list[np.ndarray] = []
        # imageio-ffmpeg starts ffmpeg with preexec_fn=os.setpgrp, which forces a fork() that can break in a
        # process running gRPC threads; without it Python spawns ffmpeg safely (vfork + exec).
        os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
        try:
            import imageio.v2 as imageio
            import imageio_ffmpeg  # noqa: F401  (provides the ffmpeg binary the MP4 writer runs)
        except ImportError:
            self.path, self._mp4 = path.with_suffix(".gif"), None
        else:
            self.path = path
            self._mp4 = imageio.get_writer(path, fps=fps, codec="libx264", macro_block_size=1, quality=7)

    def append(self, frame: np.ndarray, label: str = "") -> None:
        """Add one HxWx3 uint8 frame (`label` captions it in the strip)."""
        frame = np.asarray(frame, dtype=np.uint8)
        if self.strip_every and self._count % self.strip_every == 0:
            self._strip.append((frame, label))
        self._count += 1
        if self._mp4 is not None:
            self._mp4.append_data(frame)
        else:
            self._frames.append(frame)

    @property
    def strip_path(self) -> Path:
        """Where the frame strip goes: <stem>-strip.png beside the video."""
        return self.path.with_name(self.path.stem + "-strip.png")

    def write_strip(self) -> Path | None:
        """Every `strip_every`-th frame side by side with its caption, as a PNG (None when there is none)."""
        if not self._strip:
            return None
        from PIL import Image, ImageDraw

        h, w = self._strip[0][0].shape[:2]
        band, gap = 14, 4
        sheet = Image.new("RGB", (len(self._strip) * (w + gap) - gap, h + band), "white")
        draw = ImageDraw.Draw(sheet)
        for i, (frame, label) in enumerate(self._strip):
            x = i * (w + gap)
            sheet.paste(Image.fromarray(frame), (x, band))
            draw.text((x + 2, 1), label, fill="black")
        sheet.save(self.strip_path)
        return self.strip_path

    def close(self) -> Path:
        """Finish the file and return its path."""
        if self._mp4 is not None:
            self._mp4.close()
        elif self._frames:
            from PIL import Image

            images = [Image.fromarray(f) for f in self._frames]
            images[0].save(
                self.path, save_all=True, append_images=images[1:], duration=round(1000 / self.fps), loop=0
            )
        return self.path
