"""Where rendered frames go: an H.264 MP4 or a folder of numbered PNG files, complete or not at all."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError


class FrameSink:
    """Where frames go: an H.264 MP4 (via imageio-ffmpeg's bundled ffmpeg) or numbered PNG files.

    Output is written to a temporary name and moved into place by :meth:`commit`, so a cancelled
    or failed render never leaves a truncated video that looks finished.
    """

    def __init__(
        self, out: Path | str, width: int, height: int, fps: float, crf: int = 23, preset: str = "veryfast"
    ) -> None:
        self.out = Path(out)
        self.width, self.height, self.fps = width, height, fps
        self.count = 0
        self.is_video = self.out.suffix.lower() in (".mp4", ".m4v", ".mov", ".mkv")
        if self.out.suffix and not self.is_video:
            raise Slam6dError(f"{self.out}: output must be a .mp4 file or a directory for PNG frames")
        if not self.out.parent.is_dir():
            raise Slam6dError(f"{self.out}: the folder {self.out.parent} does not exist")
        if self.is_video:
            if width % 2 or height % 2:
                raise Slam6dError(f"{self.out}: H.264 needs an even width and height, got {width}x{height}")
            import imageio_ffmpeg

            # ffmpeg creates the file itself, so it gets the user's usual permissions.
            self._tmp = self.out.parent / f".{self.out.stem}.{os.getpid()}.{id(self):x}.partial{self.out.suffix}"
            self._writer = imageio_ffmpeg.write_frames(
                str(self._tmp),
                (width, height),
                fps=fps,
                codec="libx264",
                pix_fmt_out="yuv420p",
                quality=None,
                macro_block_size=1,
                ffmpeg_log_level="error",
                # veryfast: x264's default preset encodes 720p point clouds slower than we render them
                output_params=["-crf", str(crf), "-preset", preset, "-movflags", "+faststart"],
            )
            self._writer.send(None)
        else:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}-", dir=self.out.parent))

    def write(self, image: NDArray[np.uint8]) -> None:
        if self.is_video:
            self._writer.send(np.ascontiguousarray(image))
        else:
            from PIL import Image

            Image.fromarray(image).save(self._tmp / f"frame_{self.count:06d}.png", compress_level=1)
        self.count += 1

    def commit(self) -> Path:
        if self.is_video:
            self._writer.close()
            os.replace(self._tmp, self.out)
        else:
            self.out.mkdir(exist_ok=True)
            for frame in sorted(self._tmp.iterdir()):
                os.replace(frame, self.out / frame.name)
            self._tmp.rmdir()
        return self.out

    def discard(self) -> None:
        if self.is_video:
            with contextlib.suppress(Exception):  # ffmpeg may already have died; the file goes anyway
                self._writer.close()
            self._tmp.unlink(missing_ok=True)
        else:
            shutil.rmtree(self._tmp, ignore_errors=True)
