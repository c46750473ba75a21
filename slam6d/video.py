"""Where rendered frames go: an H.264 MP4 or a folder of numbered PNG files, complete or not at all."""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Slam6dError

# x264's presets, fastest first: each step trades encoding time for a smaller file at the same quality.
X264_PRESETS: tuple[str, ...] = (
    "ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower", "veryslow"
)  # fmt: skip


@dataclass(frozen=True)
class EncoderOptions:
    """How H.264 is written: ``preset`` buys speed with file size, ``crf`` sets the quality (0-51, lower is better).

    The default is x264's ``ultrafast``: measured on rendered point clouds at 1280x720 (noisy,
    high-detail frames) it costs 13-16 CPU ms per frame against 50-55 for ``veryfast``, at the
    same PSNR and a quarter to a third larger file. On two cores that is the difference between
    the encoder keeping up with the renderer (>= 30 fps end to end) and taking more of the CPU than
    the renderer does (``benchmarks/render.py --encoders``; docs/scale.md, "Fly-throughs").
    """

    preset: str = "ultrafast"
    crf: int = 23

    def __post_init__(self) -> None:
        if self.preset not in X264_PRESETS:
            raise ValueError(f"unknown x264 preset '{self.preset}'; choose one of {', '.join(X264_PRESETS)}")
        if not 0 <= self.crf <= 51:
            raise ValueError(f"crf must be within 0..51 (lower is better quality), got {self.crf}")


class FrameSink:
    """Where frames go: an H.264 MP4 (via imageio-ffmpeg's bundled ffmpeg) or numbered PNG files.

    Output is written to a temporary name and moved into place by :meth:`commit`, so a cancelled
    or failed render never leaves a truncated video that looks finished.

    Video frames are handed to ffmpeg by a writer thread through a bounded queue: writing a
    1280x720 frame into ffmpeg's pipe blocks until the encoder has read all 2.7 MB of it, and
    done in the render loop that wait stalled the renderer frame after frame. The thread waits
    instead, with the GIL released, while the next frame renders; ffmpeg converts RGB to YUV 4:2:0
    and encodes on its own threads. Frames are not copied on the way: the renderer draws into one
    of ``QUEUED + 1`` buffers lent by :meth:`buffer`, and the writer thread lends it out again once
    ffmpeg has read it, so :meth:`buffer` blocks (:attr:`wait_seconds`) only when the encoder is
    behind. An encoder error is raised at the next :meth:`write` or at :meth:`commit`.
    """

    QUEUED = 4  # frames rendered ahead of the encoder, at most (2.7 MB each at 720p)

    def __init__(
        self, out: Path | str, width: int, height: int, fps: float, encoder: EncoderOptions | None = None
    ) -> None:
        self.out = Path(out)
        self.width, self.height, self.fps = width, height, fps
        self.encoder = encoder or EncoderOptions()
        self.count = 0
        self.wait_seconds = 0.0  # time the caller spent waiting for a free buffer: the encoder was behind
        self.is_video = self.out.suffix.lower() in (".mp4", ".m4v", ".mov", ".mkv")
        if self.out.suffix and not self.is_video:
            raise Slam6dError(f"{self.out}: output must be a .mp4 file or a directory for PNG frames")
        if not self.out.parent.is_dir():
            raise Slam6dError(f"{self.out}: the folder {self.out.parent} does not exist")
        shape = (height, width, 3)
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
                pix_fmt_out="yuv420p",  # RGB -> YUV 4:2:0 in ffmpeg, on its threads, not in Python
                quality=None,
                macro_block_size=1,
                ffmpeg_log_level="error",
                output_params=[
                    "-crf",
                    str(self.encoder.crf),
                    "-preset",
                    self.encoder.preset,
                    "-movflags",
                    "+faststart",
                ],
            )
            self._writer.send(None)
            self._frames: queue.Queue[NDArray[np.uint8] | None] = queue.Queue(maxsize=self.QUEUED)
            self._free: queue.Queue[NDArray[np.uint8]] = queue.Queue()
            for _ in range(self.QUEUED + 1):
                self._free.put(np.empty(shape, dtype=np.uint8))
            self._failure: BaseException | None = None
            self._pump = threading.Thread(target=self._feed_encoder, name="frame-writer", daemon=True)
            self._pump.start()
        else:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}-", dir=self.out.parent))
            self._image = np.empty(shape, dtype=np.uint8)  # PNGs are written at once: one buffer serves
        self._lent: NDArray[np.uint8] | None = None

    def _feed_encoder(self) -> None:
        """The writer thread: frames from the queue into ffmpeg's pipe until the ``None`` that ends them;
        each buffer goes back to the free ones once ffmpeg has read it."""
        while (frame := self._frames.get()) is not None:
            if self._failure is None:
                try:
                    self._writer.send(frame)
                except BaseException as exc:
                    self._failure = exc
            self._free.put(frame)

    def _check_encoder(self) -> None:
        if self._failure is not None:
            raise Slam6dError(f"{self.out}: the video encoder failed: {self._failure}") from self._failure

    def buffer(self) -> NDArray[np.uint8]:
        """An (height, width, 3) image to render the next frame into and pass to :meth:`write` uncopied."""
        if not self.is_video:
            return self._image
        if self._lent is None:
            start = time.perf_counter()
            self._lent = self._free.get()
            self.wait_seconds += time.perf_counter() - start
        return self._lent

    def write(self, image: NDArray[np.uint8]) -> None:
        """Queue a frame: the buffer from :meth:`buffer` as it is, any other image as a copy (the
        caller may reuse it at once)."""
        if self.is_video:
            self._check_encoder()
            if image is not self._lent:
                target = self.buffer()
                target[...] = image
                image = target
            self._lent = None
            self._frames.put(image)
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
