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

    def __init__(self, path: Path, fps: float) -> None:
        self.fps = fps
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

    def append(self, frame: np.ndarray) -> None:
        """Add one HxWx3 uint8 frame."""
        frame = np.asarray(frame, dtype=np.uint8)
        if self._mp4 is not None:
            self._mp4.append_data(frame)
        else:
            self._frames.append(frame)

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
