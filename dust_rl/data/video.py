"""H.264 MP4 streams through PyAV (FFmpeg's libraries, bundled in the wheel).

PyAV is imported where a video is written or read: datasets and training need no video, so a machine
without PyAV (``scripts/gpu_check.sh``'s offline GPU box) still collects, trains and evaluates (``--videos 0``).
"""

from __future__ import annotations

import pathlib
from collections.abc import Iterable, Iterator

import numpy as np

from dust_rl.errors import DatasetError
from dust_rl.storage.atomic_files import atomic_write

CODEC = "libx264"  # the encoder
VIDEO_CODEC = "h264"  # the stream format it writes
PIX_FMT = "yuv420p"


def write_mp4(path: pathlib.Path, frames: Iterable[np.ndarray], fps: int, crf: int = 18,
              pad_odd: bool = False) -> int:
    """Encode RGB uint8 frames ``[H, W, 3]`` (even H and W) as one H.264 stream; returns the frame count.

    Frame ``i`` gets presentation time ``i / fps``, so a frame's index is its timestamp times ``fps``.
    With ``pad_odd`` (videos to watch, not data) an odd height or width gets one more row or column,
    repeated from the edge. Written atomically: an earlier video at ``path`` stays until the new one is whole.
    """
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    with atomic_write(path, "wb") as file, av.open(file, "w", format="mp4") as container:
        stream = None
        for frame in frames:
            if pad_odd:
                frame = np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)), mode="edge")
            if stream is None:
                height, width = frame.shape[:2]
                if height % 2 or width % 2:
                    raise ValueError(f"H.264 ({PIX_FMT}) needs even image sizes, got {height}x{width}")
                stream = container.add_stream(CODEC, rate=fps)
                stream.width, stream.height, stream.pix_fmt = width, height, PIX_FMT
                stream.options = {"crf": str(crf)}
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")):
                container.mux(packet)
            count += 1
        if stream is not None:
            for packet in stream.encode():
                container.mux(packet)
    return count


def read_mp4(path: pathlib.Path, size: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
    """Decoded RGB uint8 frames ``[H, W, 3]`` of the first video stream, in order.

    Args:
        path: the file.
        size: the ``(H, W)`` every frame must have; checked before a frame is converted, so a
            video from elsewhere cannot make the reader allocate frames of any size it likes.

    Raises:
        DatasetError: an undecodable file, or a frame of another size.
    """
    import av

    try:
        with av.open(str(path)) as container:
            for frame in container.decode(video=0):
                if size is not None and (frame.height, frame.width) != tuple(size):
                    raise DatasetError(f"{path}: frames are {frame.height}x{frame.width}, expected "
                                       f"{size[0]}x{size[1]}")
                yield frame.to_ndarray(format="rgb24")
    except (av.FFmpegError, OSError) as err:
        raise DatasetError(f"{path}: cannot decode video ({err})") from err
