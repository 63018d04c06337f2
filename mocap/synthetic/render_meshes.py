"""Drawing a session whose links are `mocap.synthetic.meshes` solids, not the tracker's boxes.

Links far to near (by the centre of their bodies), each its bodies' faces far to near, then
its marker plates, the markers the truth calls partly visible, and its hoses and rails;
shadows are cast by the bodies on the bodies. Painting whole links far to near is wrong where
links overlap on the picture (a nearer link's body, or a hose, painted over a marker in front
of it): the markers the truth calls wholly in view (every point of
`mocap.synthetic.meshes.marker_test_points` unhidden) are painted last, over everything, so
that the picture shows what the truth says. The rest (backdrop, motion blur, rolling shutter, the
camera's effects) is `mocap.synthetic.render.CameraRenderer`'s.

Shapes: F frames, S solids, M markers.
"""

from __future__ import annotations

import cv2
import numpy as np

from mocap.core.shapes import BOX_FACES
from mocap.core.visibility import marker_outlines
from mocap.synthetic.meshes import marker_test_points, solids_in_view
from mocap.synthetic.render import CameraRenderer, RenderOptions, draw_marker
from mocap.synthetic.session import SyntheticSession, marker_sizes

HOSE = np.array([42.0, 42.0, 46.0])  # BGR


class MeshRenderer(CameraRenderer):
    """`CameraRenderer` for a session with `solids`."""

    def __init__(self, session: SyntheticSession, index: int, options: RenderOptions, rng: np.random.Generator):
        super().__init__(session, index, options, rng)
        solids = session.solids
        self.solids = solids
        self.corners = solids.corners
        self.local_normals = solids.face_normals
        palette = self.look.palette
        colours = palette[solids.links % len(palette)]
        self.colours = np.where((solids.kind == 2)[:, None], HOSE, colours)
        self.bodies = np.flatnonzero(solids.kind == 0)
        # the points the truth tests for a marker wholly in view (`make_session`'s scores)
        self.test_points = marker_test_points(*marker_outlines(session.machine, session.normals,
                                                               *marker_sizes(session.reach), n_points=16))

    def _view(self, at: np.ndarray):
        machine = self.session.machine
        cams = self.field.cam_from_world(self.field.times(at))
        _, seen, poses = self.session.observe(self.field, at)
        camera = self.field.camera
        whole = np.zeros_like(seen)
        if np.any(seen):
            shown = solids_in_view(machine, self.solids, self.session.normals, poses, cams, camera.matrix,
                                   camera.distortion, camera.size, self.test_points)[1]
            whole = seen & np.all(shown, axis=-1)
        centres = -np.einsum("fji,fj->fi", cams[:, :3, :3], cams[:, :3, 3])
        on_solid = poses[:, self.solids.links]
        corners = np.einsum("fsij,skj->fski", on_solid[..., :3, :3], self.corners) + on_solid[:, :, None, :3, 3]
        normals = np.einsum("fsij,skj->fski", on_solid[..., :3, :3], self.local_normals)
        on_link = poses[:, machine.marker_links]
        squares = np.einsum("fmij,mnj->fmni", on_link[..., :3, :3], self.squares) + on_link[..., None, :3, 3]
        disks = np.einsum("fmij,mnj->fmni", on_link[..., :3, :3], self.disks) + on_link[..., None, :3, 3]
        return (centres, corners, normals, self._project(cams, corners), self._project(cams, squares),
                self._project(cams, disks), seen, cams, whole)

    def _draw_machine(self, image, centre, corners, normals, uv_corners, uv_squares, uv_disks, seen, cam, whole,
                      rows: tuple[int, int] | None = None) -> None:
        solids = self.solids
        distance = np.linalg.norm(corners.mean(axis=1) - centre, axis=-1)  # (S,)
        n_links = int(solids.links.max()) + 1
        link_distance = np.array([distance[(solids.links == l) & (solids.kind == 0)].min(initial=np.inf)
                                  for l in range(n_links)])
        for l in np.argsort(-link_distance):
            own = np.flatnonzero(solids.links == l)
            for kind in (0, 1, 2):
                for s in own[solids.kind[own] == kind][np.argsort(-distance[own[solids.kind[own] == kind]])]:
                    self._draw_solid(image, s, centre, corners, normals, uv_corners)
                    if kind == 0 and self.look.shadows:
                        k = int(np.searchsorted(self.bodies, s))
                        self._cast_shadows(image, k, centre, corners[self.bodies], normals[self.bodies], cam)
                if kind == 1:
                    for m in np.flatnonzero(seen & ~whole & (self.session.machine.marker_links == l)):
                        self._draw_marker(image, m, uv_squares, uv_disks)
        for m in np.flatnonzero(whole):
            self._draw_marker(image, m, uv_squares, uv_disks)

    def _draw_marker(self, image, m, uv_squares, uv_disks) -> None:
        white = None if np.isnan(self.square_grey[m]) else float(self.square_grey[m])
        draw_marker(image, uv_squares[m], uv_disks[m], self.options.supersample, white, self.look.disk_grey)

    def _draw_solid(self, image, s, centre, corners, normals, uv_corners) -> None:
        for f, quad in enumerate(BOX_FACES):
            if normals[s, f] @ (centre - corners[s, quad].mean(axis=0)) <= 0:
                continue
            pts = uv_corners[s, quad]
            if not np.all(np.isfinite(pts)) or np.abs(pts).max() > 1e5:
                continue
            shade = self.look.shade(float(normals[s, f] @ self.sun))
            cv2.fillPoly(image, [np.round(pts * 16).astype(np.int32)], (self.colours[s] * shade).tolist(),
                         lineType=cv2.LINE_AA, shift=4)
