"""Where rendered frames go: an H.264 MP4 or a folder of numbered PNG files, complete or not at all."""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError


class FrameSink:
    """Where frames go: an H.264 MP4 (via imageio-ffmpeg's bundled ffmpeg) or numbered PNG files.

    Output is written to a temporary name and moved into place by :meth:`commit`, so a cancelled
    or failed render never leaves a truncated video that looks finished.

    Video frames are handed to ffmpeg by a writer thread through a queue of ``QUEUED`` frames:
    writing a 1280x720 frame into ffmpeg's pipe blocks until the encoder has read all 2.7 MB of it,
    and done in the render loop that wait stalled the renderer frame after frame (a 60-frame
    clip: 15 fps end to end against 72 fps rendering alone). The thread waits instead, with the
    GIL released, while the next frame renders; an encoder error is raised at the next
    :meth:`write` or at :meth:`commit`.
    """

    QUEUED = 4  # frames rendered ahead of the encoder, at most (2.7 MB each at 720p)

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
            self._frames: queue.Queue[NDArray[np.uint8] | None] = queue.Queue(maxsize=self.QUEUED)
            self._failure: BaseException | None = None
            self._pump = threading.Thread(target=self._feed_encoder, name="frame-writer", daemon=True)
            self._pump.start()
        else:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}-", dir=self.out.parent))

    def _feed_encoder(self) -> None:
        """The writer thread: frames from the queue into ffmpeg's pipe until the ``None`` that ends them."""
        while (frame := self._frames.get()) is not None:
            if self._failure is None:
                try:
                    self._writer.send(frame)
                except BaseException as exc:
                    self._failure = exc

    def _check_encoder(self) -> None:
        if self._failure is not None:
            raise Slam6dError(f"{self.out}: the video encoder failed: {self._failure}") from self._failure

    def write(self, image: NDArray[np.uint8]) -> None:
        if self.is_video:
            self._check_encoder()
            self._frames.put(np.array(image, order="C", copy=True))  # the renderer reuses its image buffer
        else:
            from PIL import Image

            Image.fromarray(image).save(self._tmp / f"frame_{self.count:06d}.png", compress_level=1)
        self.count += 1

    def _drain(self) -> None:
        """Let the writer thread send what is queued and stop."""
        if self._pump.is_alive():
            self._frames.put(None)
            self._pump.join()

    def commit(self) -> Path:
        if self.is_video:
            self._drain()
            self._check_encoder()
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
            self._failure = self._failure or Slam6dError("discarded")  # the thread sends nothing more
            self._drain()
            with contextlib.suppress(Exception):  # ffmpeg may already have died; the file goes anyway
                self._writer.close()
            self._tmp.unlink(missing_ok=True)
        else:
            shutil.rmtree(self._tmp, ignore_errors=True)
