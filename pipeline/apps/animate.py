"""Mode shapes moving: ``python -m pipeline plot FILE.h5 --animate``.

One animation per mode, the body drawn as in :mod:`pipeline.apps.plots` (by
:mod:`pipeline.apps.mode_drawing`: 3D perspective, or for a slender body the side /
end-on view) with the deformation ``sin(2 pi k / frames) * scale * phi`` in frame k (one
period, ``frames`` frames, looped), ``scale`` making the largest displacement
:data:`~pipeline.apps.mode_drawing.DEFORMATION_FRACTION` of the body's size. Written as GIF (matplotlib's PillowWriter) and, where ffmpeg is
installed, also as MP4; every file through the atomic writer.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from pipeline._util.atomic import atomic_path
from pipeline.apps import mode_drawing as drawing

log = logging.getLogger(__name__)

FRAMES = 24
FPS = 12
DPI = 80


def ffmpeg_available() -> bool:
    """True when an ffmpeg executable is on PATH (MP4 output)."""
    return shutil.which("ffmpeg") is not None


def _frames(fig, data, surface, mode: int, frames: int):
    """Yield once per frame after drawing it into ``fig``."""
    slender = drawing.is_slender(data.points)
    for k in range(frames):
        amplitude = float(np.sin(2 * np.pi * k / frames))
        fig.clear()
        if slender:
            ax = fig.add_subplot()
            fig.subplots_adjust(left=0.12, right=0.97, top=0.86, bottom=0.16)
            drawing.draw_mode_2d(ax, data, surface, mode, amplitude=amplitude)
        else:
            ax = fig.add_subplot(projection="3d", computed_zorder=False)
            drawing.draw_mode(ax, data, surface, mode, amplitude=amplitude)
        fig.suptitle(drawing.mode_title(data, mode), fontsize=12, fontweight="bold")
        yield k


def animate_mode(data, mode: int, out: str | Path, surface=None, frames: int = FRAMES,
                 fps: int = FPS, mp4: bool | None = None) -> list[Path]:
    """Write the animation of mode ``mode`` (0-based) to ``out`` (.gif) and, where ffmpeg
    is present (or ``mp4`` is True), its .mp4 twin; returns the files written."""
    from matplotlib.animation import FFMpegWriter, PillowWriter
    from matplotlib.figure import Figure

    out = Path(out)
    surface = surface or drawing.boundary_surface(data.points, data.cells, subdivide_below=0)
    slender = drawing.is_slender(data.points)
    fig = Figure(figsize=(7.0, 3.8) if slender else (6.0, 5.0), dpi=DPI, facecolor="white")
    written = []
    targets = [(out.with_suffix(".gif"), PillowWriter(fps=fps))]
    if mp4 if mp4 is not None else ffmpeg_available():
        targets.append((out.with_suffix(".mp4"), FFMpegWriter(fps=fps)))
    for path, writer in targets:
        with atomic_path(path) as tmp, writer.saving(fig, str(tmp), DPI):
            for _ in _frames(fig, data, surface, mode, frames):
                writer.grab_frame(facecolor="white")
        written.append(path)
        log.info("wrote %s", path)
    return written
