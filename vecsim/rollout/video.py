"""Videos of chosen trajectories: the frames of one camera gathered as a rollout runs, written as
MP4 (imageio with its ffmpeg, the ``demo`` extra).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vecsim.client import StageBatch


class Recorder:
    """Frames of one camera for the trajectories chosen for video."""

    def __init__(self, keys: list[str], camera: str | None) -> None:
        self.frames: dict[str, list[np.ndarray]] = {key: [] for key in keys}
        self.camera = camera

    def add(self, key: str, batch: StageBatch, row: int) -> None:
        """Take the frames of a reset or step answer: a chunk's recorded frames, one per applied
        action, or else the observation's."""
        if key not in self.frames:
            return
        chunk = batch.frames.get(key)
        if chunk is not None:
            self.frames[key].extend(np.array(frame) for frame in chunk[self.camera][: int(batch.num_steps[row])])
        else:
            self.frames[key].append(np.array(batch.obs["images"][self.camera][row]))


def write_video(path: str | Path, frames: Sequence[np.ndarray], fps: int = 10) -> Path:
    """Write uint8 ``HxWx3`` frames to ``path``: ``.gif`` with Pillow, anything else with ffmpeg.

    Returns the path written.

    Raises:
        ValueError: no frames, or frames that are not uint8 ``HxWx3`` of one size.
    """
    path = Path(path)
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1 or len(next(iter(shapes))) != 3 or next(iter(shapes))[2] != 3:
        raise ValueError(f"{path}: frames must be HxWx3 of one size, got shapes {sorted(shapes)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        from PIL import Image

        images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
        return path
    import imageio.v2 as imageio

    height, width, _ = next(iter(shapes))
    # yuv420p needs even sides: pad by one edge pixel rather than let ffmpeg rescale.
    pad = ((0, height % 2), (0, width % 2), (0, 0))
    with imageio.get_writer(path, fps=fps, codec="libx264", macro_block_size=1, pixelformat="yuv420p") as writer:
        for frame in frames:
            writer.append_data(np.pad(np.asarray(frame, dtype=np.uint8), pad, mode="edge"))
    return path
