"""What a calibration's data leave doubtful: cameras they hardly fix, cameras many of whose
observations disagree with the fit, and (with a tolerance, whose offsets can absorb the
perspective) cameras they do not fix at all, which are refused rather than returned.

Each takes a `CalibrationResult` (mocap.calibration.solve).
"""

from __future__ import annotations

import logging

import numpy as np

from mocap.errors import DegenerateError

log = logging.getLogger(__name__)


ORTHOGRAPHIC_WIDTHS = 100.0  # a focal length beyond this many image widths (a 0.6° view): the orthographic limit


def far_cameras(result) -> list[str]:
    """Cameras whose focal length went beyond ORTHOGRAPHIC_WIDTHS image widths (eight times
    the start's search): towards the orthographic limit, where focal length and distance
    are no longer told apart."""
    return [c.name for c in result.cameras if c.focal > ORTHOGRAPHIC_WIDTHS * c.size[0]]


def doubtful_cameras(result) -> list[int]:
    """Cameras that lost more than a fifth (and at least two) of their observations as
    outliers: more than wrong detections explain."""
    out = []
    for c, camera in enumerate(result.cameras):
        mine = [r.outlier for r in result.residuals if r.camera == camera.name]
        if sum(mine) >= 2 and sum(mine) > 0.2 * len(mine):
            out.append(c)
    return out


def warnings(result) -> tuple[str, ...]:
    """One sentence per thing the data leave doubtful: a camera whose position they hardly
    fix (its standard deviation beyond a tenth of its distance: focal length and distance
    barely told apart), a camera many of whose observations disagree with the fit."""
    out = []
    target = np.mean(result.markers_world, axis=0)
    for c, camera in enumerate(result.cameras):
        distance = float(np.linalg.norm(camera.center - target))
        sd = float(np.linalg.norm(result.paper_sd[c][3:6]))
        if not sd <= 0.1 * distance:
            out.append(f"camera {camera.name}: its position is hardly fixed by these markers (± {sd:.2f} m at "
                       f"{distance:.1f} m; focal length and distance barely told apart): use a frame where the "
                       "machine shows more depth or more markers, another camera, or known intrinsics")
    for c in doubtful_cameras(result):
        name = result.cameras[c].name
        mine = [r.outlier for r in result.residuals if r.camera == name]
        out.append(f"camera {name}: {sum(mine)} of its {len(mine)} observations disagree with the fit: check "
                   "its marker labels; its solution is doubtful")
    for line in out:
        log.warning("%s", line)
    return tuple(out)


def refuse_unfixed(result) -> None:
    """Raises DegenerateError for a camera the data do not fix: its focal length gone to the
    orthographic limit, or its position's standard deviation beyond its distance."""
    target = np.mean(result.markers_world, axis=0)
    for c, camera in enumerate(result.cameras):
        distance = float(np.linalg.norm(camera.center - target))
        sd = float(np.linalg.norm(result.paper_sd[c][3:6]))
        if camera.name in far_cameras(result) or not sd <= distance:
            raise DegenerateError(
                f"focal length and distance of camera {camera.name} cannot be told apart (its position "
                f"± {sd:.3g} m at {distance:.3g} m, focal length {camera.focal:.3g} px): these markers do not "
                "fix it; use a frame where the machine shows more depth or more markers, another camera, "
                "or known intrinsics"
            )
