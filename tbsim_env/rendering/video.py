"""Writing frame sequences to MP4 (H.264, yuv420p) or GIF, and logged-scenario videos."""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from tbsim_env.data.scenario import Scenario
from tbsim_env.rendering.frame import render_log_frame
from tbsim_env.rendering.map_layer import MapLayer
from tbsim_env.rendering.view import view_for

VIDEO_EXTENSIONS = (".mp4", ".gif")
"""Supported output formats, chosen by the path's extension."""
MP4_QUALITY = 8
"""imageio-ffmpeg quality 0..10 (10 = best); 8 keeps thin map lines crisp."""


def _check_frame(frame: np.ndarray, index: int, shape: tuple[int, ...] | None) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(
            f"frame {index}: expected a uint8 [H, W, 3] array, got {arr.dtype} {arr.shape}"
        )
    if shape is not None and arr.shape != shape:
        raise ValueError(f"frame {index} has shape {arr.shape}, the first frame had {shape}")
    return arr


def pad_even(frame: np.ndarray) -> np.ndarray:
    """Pad [H, W, 3] on the bottom/right by repeating the edge so that H and W are even."""
    h, w = frame.shape[:2]
    ph, pw = h % 2, w % 2
    if ph == 0 and pw == 0:
        return frame
    return np.pad(frame, ((0, ph), (0, pw), (0, 0)), mode="edge")


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 10) -> int:
    """Write frames to an MP4 (H.264, yuv420p) or an animated GIF, chosen by extension.

    MP4 frames are streamed to ffmpeg one at a time and padded to even sizes (yuv420p needs
    them); GIF frames are collected in memory, palette-quantised and looped forever.

    Args:
        frames: uint8 [H, W, 3] RGB arrays, all of one shape.
        path: output file; ``.mp4`` or ``.gif`` (case-insensitive). Parent folders are created.
        fps: frames per second (> 0).

    Returns:
        The number of frames written.

    Raises:
        ValueError: unknown extension, bad fps, no frames, or a malformed / mismatched frame.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in VIDEO_EXTENSIONS:
        raise ValueError(
            f"cannot write video {str(path)!r}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(VIDEO_EXTENSIONS)}"
        )
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    path.parent.mkdir(parents=True, exist_ok=True)
    it: Iterator[np.ndarray] = iter(frames)
    first = next(it, None)
    if first is None:
        raise ValueError(f"cannot write video {str(path)!r}: no frames")
    first = _check_frame(first, 0, None)
    shape = first.shape

    if ext == ".gif":
        images = [Image.fromarray(first)]
        for i, f in enumerate(it, start=1):
            images.append(Image.fromarray(_check_frame(f, i, shape)))
        images[0].save(
            path,
            save_all=True,
            append_images=images[1:],
            duration=max(1, int(round(1000.0 / fps))),
            loop=0,
            optimize=False,
        )
        return len(images)

    import imageio.v2 as imageio

    count = 0
    writer = imageio.get_writer(
        str(path),
        format="FFMPEG",  # type: ignore[arg-type]
        mode="I",
        fps=fps,
        codec="libx264",
        pixelformat="yuv420p",
        quality=MP4_QUALITY,
        macro_block_size=1,
        ffmpeg_log_level="error",
    )
    try:
        writer.append_data(pad_even(first))
        count = 1
        for i, f in enumerate(it, start=1):
            writer.append_data(pad_even(_check_frame(f, i, shape)))
            count += 1
    finally:
        writer.close()
    return count


def render_log_video(
    scenario: Scenario,
    path: str | os.PathLike,
    *,
    size: tuple[int, int] = (600, 600),
    fps: float = 10,
    trail_steps: int = 10,
    progress: bool = True,
) -> Path:
    """Render the logged scenario (every track replayed, the SDC highlighted) to a video.

    Args:
        scenario: the scenario.
        path: ``.mp4`` or ``.gif`` output.
        size: (H, W) pixels.
        fps: frames per second (10 = real time for WOMD).
        trail_steps: past steps drawn as trails.
        progress: show a tqdm progress bar.

    Returns:
        The output path.
    """
    path = Path(path)
    if path.suffix.lower() not in VIDEO_EXTENSIONS:
        raise ValueError(
            f"cannot write video {str(path)!r}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(VIDEO_EXTENSIONS)}"
        )
    layer = MapLayer.build(scenario, view_for(scenario, size))
    steps = tqdm(
        range(scenario.num_steps),
        desc=f"render {scenario.scenario_id}",
        unit="frame",
        disable=not progress,
    )
    write_video(
        (render_log_frame(layer, scenario, t, trail_steps=trail_steps) for t in steps), path, fps
    )
    return path
