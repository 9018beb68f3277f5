"""H.264 video of a recording's windows, one frame per window, encoded by PyAV (the ``video`` extra).

PyAV binds FFmpeg's libraries in process and its wheels carry their own FFmpeg, so nothing is
installed system-wide and no ``ffmpeg`` subprocess is piped to. Frames are the RGB images of
:func:`evseg_torch.viz.panels.render_fig1`; they are padded with white to even sizes, which H.264's
4:2:0 chroma needs. A frame per window at :data:`FRAMES_PER_SECOND` plays slower than real time (a
30 ms window lasts 0.1 s on screen), so that each window's clusters can be read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evseg_torch.errors import EvsegError, ShapeError

FRAMES_PER_SECOND = 10


def require_av():
    """PyAV's module, or a one-line error naming the extra to install."""
    try:
        import av
    except ImportError:
        raise EvsegError("--video needs PyAV: pip install 'evseg-torch[video]'") from None
    return av


class VideoWriter:
    """Append RGB frames of one size to an MP4 file (H.264, yuv420p).

    Args:
        path: the ``.mp4`` file; replaced if it exists.
        fps: frames per second.

    The frame size is fixed by the first frame; a later frame of another size is an error.
    """

    def __init__(self, path: str | Path, fps: int = FRAMES_PER_SECOND):
        self.path = Path(path)
        self.fps = fps
        self.n_frames = 0
        self._container = require_av().open(str(self.path), mode="w")
        self._stream = None

    def write(self, frame: np.ndarray) -> None:
        """Append one uint8 :math:`(H, W, 3)` RGB frame."""
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ShapeError(f"video frames must be uint8 (H, W, 3) RGB, got {frame.dtype} {frame.shape}")
        height, width = frame.shape[0] + frame.shape[0] % 2, frame.shape[1] + frame.shape[1] % 2
        if self._stream is None:
            self._stream = self._container.add_stream("libx264", rate=self.fps)
            self._stream.width, self._stream.height = width, height
            self._stream.pix_fmt = "yuv420p"
            self._stream.options = {"crf": "20", "preset": "veryfast"}
        elif (height, width) != (self._stream.height, self._stream.width):
            raise ShapeError(
                f"video frames must all be {self._stream.height}x{self._stream.width}, got {frame.shape[:2]}"
            )
        padded = np.full((height, width, 3), 255, dtype=np.uint8)
        padded[: frame.shape[0], : frame.shape[1]] = frame
        av_frame = require_av().VideoFrame.from_ndarray(padded, format="rgb24")
        for packet in self._stream.encode(av_frame):
            self._container.mux(packet)
        self.n_frames += 1

    def close(self) -> None:
        """Flush the encoder and finish the file; closing again does nothing."""
        if self._container is None:
            return
        if self._stream is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
        self._container.close()
        self._container = None


def read_frames(path: str | Path) -> list[np.ndarray]:
    """Decode every frame of a video as uint8 :math:`(H, W, 3)` RGB (for checks and notebooks)."""
    with require_av().open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
