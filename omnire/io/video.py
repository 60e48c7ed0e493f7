"""Writing videos: MP4 (H.264, yuv420p) through imageio-ffmpeg, which bundles an ffmpeg
binary, so nothing is downloaded or looked up at run time.

Frames are streamed to ffmpeg as they are rendered (:class:`Mp4Writer`), into a temporary
file beside the target that is renamed over it only when the video is complete: an
interrupted render leaves no half-written MP4 under the final name.

H.264 in yuv420p needs an even width and height; an odd-sized frame is padded by repeating
its last column / row (never resampled), so the video is at most one pixel larger.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable, Optional

import numpy as np
import torch

from omnire.errors import ConfigError, UserError
from omnire.io.atomic import current_umask


class VideoWriteError(UserError):
    """The video could not be written (ffmpeg failed, disk full, ...); the message names the file."""


def _to_uint8(frame: "torch.Tensor | np.ndarray") -> np.ndarray:
    """(H, W, 3) float in [0, 1] or uint8 -> contiguous uint8 (H, W, 3)."""
    arr = frame.detach().cpu().numpy() if torch.is_tensor(frame) else np.asarray(frame)
    if arr.ndim != 3 or arr.shape[2] not in (1, 3):
        raise ValueError(f"video frame: shape {arr.shape}, expected (H, W, 3) or (H, W, 1)")
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return arr


def _pad_even(arr: np.ndarray) -> np.ndarray:
    h, w = arr.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return np.ascontiguousarray(arr)
    return np.ascontiguousarray(np.pad(arr, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))


class Mp4Writer:
    """Stream frames into an H.264 MP4 at ``path``, renamed into place on :meth:`close`.

    Args:
        path: the target ``.mp4`` file (its directory is created).
        fps: frames per second (> 0).
        crf: x264 constant rate factor (0 = lossless .. 51; 18 is visually lossless).
        preset: x264 speed preset.

    Use as a context manager; an exception inside the ``with`` block discards the
    temporary file and leaves any existing ``path`` untouched::

        with Mp4Writer(out / "front.mp4", fps=10) as video:
            for image in images:          # (H, W, 3) float in [0, 1] or uint8
                video.append(image)
    """

    def __init__(self, path: str | Path, fps: float, crf: int = 18, preset: str = "fast") -> None:
        if not fps > 0:
            raise ConfigError(f"video fps {fps}: must be > 0")
        if not 0 <= crf <= 51:
            raise ConfigError(f"video crf {crf}: must be in 0..51")
        self.path = Path(path)
        self.fps = float(fps)
        self.crf = int(crf)
        self.preset = preset
        self.frames = 0
        self.size: Optional[tuple[int, int]] = None  # (width, height) of the frames given
        self._gen = None
        self._tmp: Optional[str] = None

    def _open(self, width: int, height: int) -> None:
        import imageio_ffmpeg

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self._tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.stem}.", suffix=".tmp.mp4")
        os.close(fd)
        self._gen = imageio_ffmpeg.write_frames(
            self._tmp, (width + width % 2, height + height % 2), fps=self.fps, codec="libx264", quality=None,
            pix_fmt_in="rgb24", pix_fmt_out="yuv420p", macro_block_size=1, ffmpeg_log_level="error",
            output_params=["-crf", str(self.crf), "-preset", self.preset, "-movflags", "+faststart"])
        self._gen.send(None)  # start ffmpeg

    def append(self, frame: "torch.Tensor | np.ndarray") -> None:
        """Add one (H, W, 3) frame (float in [0, 1], or uint8); every frame has the first's size."""
        arr = _to_uint8(frame)
        h, w = arr.shape[:2]
        if self.size is None:
            self.size = (w, h)
            self._open(w, h)
        elif self.size != (w, h):
            raise ValueError(f"{self.path}: frame {self.frames} is {w}x{h}, the video is {self.size[0]}x{self.size[1]}")
        try:
            self._gen.send(_pad_even(arr))
        except (OSError, RuntimeError) as exc:
            self.abort()
            raise VideoWriteError(f"{self.path}: ffmpeg failed while writing frame {self.frames} ({exc})") from None
        self.frames += 1

    def close(self) -> None:
        """Finish the video and move it into place (a video needs at least one frame)."""
        if self._gen is None:
            raise VideoWriteError(f"{self.path}: no frames were given; nothing written")
        try:
            self._gen.close()
        except (OSError, RuntimeError) as exc:
            self.abort()
            raise VideoWriteError(f"{self.path}: ffmpeg failed to finish the video ({exc})") from None
        self._gen = None
        os.chmod(self._tmp, 0o666 & ~current_umask())
        os.replace(self._tmp, self.path)
        self._tmp = None

    def abort(self) -> None:
        """Stop ffmpeg and delete the temporary file; ``path`` is left as it was."""
        if self._gen is not None:
            try:
                self._gen.close()
            except Exception:  # noqa: BLE001 - we are discarding the output anyway
                pass
            self._gen = None
        if self._tmp is not None and os.path.exists(self._tmp):
            os.unlink(self._tmp)
        self._tmp = None

    def __enter__(self) -> "Mp4Writer":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_mp4(path: str | Path, frames: Iterable["torch.Tensor | np.ndarray"], fps: float, crf: int = 18) -> int:
    """Write ``frames`` ((H, W, 3) each) to an H.264 MP4 at ``path`` atomically; returns
    the number of frames written."""
    with Mp4Writer(path, fps, crf) as video:
        for frame in frames:
            video.append(frame)
    return video.frames


def read_mp4(path: str | Path) -> tuple[np.ndarray, float]:
    """Decode an MP4 (for checks): frames (T, H, W, 3) uint8 and the stream's fps."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    w, h = meta["size"]
    frames = [np.frombuffer(buf, np.uint8).reshape(h, w, 3) for buf in reader]
    return (np.stack(frames) if frames else np.zeros((0, h, w, 3), np.uint8)), float(meta["fps"])
