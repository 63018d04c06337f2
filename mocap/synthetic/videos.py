"""A synthetic session's videos: each camera's frames drawn by its renderer (the link boxes,
or other solids, `mocap.synthetic.render_meshes`) and encoded to videos/<camera>.mp4."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from mocap.progress import progress
from mocap.synthetic.encode import video_writer
from mocap.synthetic.render import CameraRenderer, RenderOptions
from mocap.synthetic.render_meshes import MeshRenderer
from mocap.synthetic.session import SyntheticSession

log = logging.getLogger(__name__)


def renderer_for(session: SyntheticSession, index: int, options: RenderOptions,
                 rng: np.random.Generator) -> CameraRenderer:
    """The renderer of camera `index`: `CameraRenderer`, or for a session whose links are
    drawn as other solids (`SessionOptions.shapes`), `mocap.synthetic.render_meshes.MeshRenderer`."""
    if session.solids is None:
        return CameraRenderer(session, index, options, rng)
    return MeshRenderer(session, index, options, rng)


def render_videos(session: SyntheticSession, root: str | Path, options: RenderOptions | None = None) -> list[Path]:
    """Write videos/<camera>.mp4 for every camera of the session; returns the paths."""
    options = options or RenderOptions()
    rng = np.random.default_rng([session.options.seed, 1])
    paths = []
    total = sum(c.frames for c in session.cameras)
    with progress(total=total, desc="rendering", unit="frame") as bar:
        for index, camera in enumerate(session.cameras):
            renderer = renderer_for(session, index, options, rng)
            path = Path(root) / "videos" / f"{camera.name}.mp4"
            with video_writer(path, camera.camera.size, camera.fps, options.codec, options.threads,
                              options.look.crf) as write:
                for _, image in renderer.frames():
                    write(image)
                    bar.update(1)
            log.info("wrote %s (%d frames)", path, camera.frames)
            paths.append(path)
    return paths
