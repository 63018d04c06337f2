"""COLMAP models and camera files, through pycolmap: the one module that calls pycolmap.

Conventions, and where they differ from ours:
- Pixels: COLMAP's origin is the top-left corner of the top-left pixel, OpenCV's its centre,
  so a COLMAP pixel (and principal point) is the OpenCV one + 0.5.
- Poses: an image's `cam_from_world` is ours (x_cam = R X_world + t, OpenCV camera axes);
  COLMAP's text files store its rotation as a quaternion in w, x, y, z order (pycolmap's
  Rotation3d takes x, y, z, w): we hand pycolmap the matrix and let it write the file.
- Lenses: our 5 OpenCV coefficients (k1, k2, p1, p2, k3) are COLMAP's PINHOLE (none),
  OPENCV (k3 = 0) or FULL_OPENCV (k4 = k5 = k6 = 0). COLMAP has no skew.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocap.core.camera import Camera
from mocap.errors import InputError
from mocap.io.text import read_text

PIXEL_OFFSET = 0.5  # COLMAP pixel = OpenCV pixel + 0.5

# model name -> (parameter names); f: one focal length for both axes
_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


@dataclass(frozen=True)
class ColmapCamera:
    """A COLMAP camera in our terms: id, size (w, h), K (3, 3) in OpenCV pixels, distortion (5,)."""

    camera_id: int
    size: tuple[int, int]
    matrix: np.ndarray
    distortion: np.ndarray


def colmap_params(camera: Camera) -> tuple[str, list[float]]:
    """COLMAP model name and parameters (COLMAP pixels) of one of our cameras."""
    matrix, (k1, k2, p1, p2, k3) = camera.matrix, camera.distortion
    if matrix[0, 1] != 0.0:
        raise InputError(f"camera {camera.name!r} has skew {matrix[0, 1]}: COLMAP models have none")
    fx, fy = matrix[0, 0], matrix[1, 1]
    cx, cy = matrix[0, 2] + PIXEL_OFFSET, matrix[1, 2] + PIXEL_OFFSET  # OpenCV -> COLMAP pixels
    if not np.any(camera.distortion):
        return "PINHOLE", [fx, fy, cx, cy]
    if k3 == 0.0:
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]


def intrinsics_from_params(model: str, params, camera_id: int, size, where: str) -> ColmapCamera:
    """Our K and distortion from a COLMAP model's parameters (COLMAP pixels)."""
    if model not in _MODELS:
        raise InputError(f"camera model {model} is not supported; use one of {', '.join(_MODELS)}", where=where)
    names = _MODELS[model]
    if len(params) != len(names):
        raise InputError(f"{model} has {len(names)} parameters ({', '.join(names)}), got {len(params)}", where=where)
    value = dict(zip(names, (float(p) for p in params)))
    if any(value.get(k, 0.0) != 0.0 for k in ("k4", "k5", "k6")):
        raise InputError("FULL_OPENCV with k4, k5 or k6 is not supported (rational model)", where=where)
    fx, fy = value.get("fx", value.get("f")), value.get("fy", value.get("f"))
    cx, cy = value["cx"] - PIXEL_OFFSET, value["cy"] - PIXEL_OFFSET  # COLMAP -> OpenCV pixels
    matrix = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    distortion = np.array([value.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
    return ColmapCamera(int(camera_id), (int(size[0]), int(size[1])), matrix, distortion)


def read_cameras_text(path: str | Path) -> list[ColmapCamera]:
    """COLMAP's cameras.txt: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` a line, # comments."""
    path = Path(path)
    cameras = []
    for line_no, line in enumerate(read_text(path, "check the cameras.txt path").splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split()
        where = f"{path}: line {line_no}"
        try:
            camera_id, model, width, height = int(fields[0]), fields[1], int(fields[2]), int(fields[3])
            params = [float(v) for v in fields[4:]]
        except (ValueError, IndexError):
            raise InputError("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...", where=where) from None
        cameras.append(intrinsics_from_params(model, params, camera_id, (width, height), where))
    if not cameras:
        raise InputError("no cameras in the file", path=path)
    return cameras


def read_model_cameras(folder: str | Path) -> dict[str, ColmapCamera]:
    """The cameras of a COLMAP model folder (binary or text), by name: the folder that all
    of a camera's images share (``cam1/000001.png`` -> ``cam1``), else the camera id."""
    import pycolmap

    folder = Path(folder)
    try:
        model = pycolmap.Reconstruction(folder)
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"not a COLMAP model folder ({exc})", path=folder) from None
    folders: dict[int, set[str]] = {}
    for image in model.images.values():
        head = image.name.split("/")[0] if "/" in image.name else ""
        folders.setdefault(image.camera_id, set()).add(head)
    out = {}
    for camera_id, camera in sorted(model.cameras.items()):
        heads = folders.get(camera_id, set())
        name = next(iter(heads)) if len(heads) == 1 and "" not in heads else str(camera_id)
        if name in out:
            name = str(camera_id)
        out[name] = intrinsics_from_params(
            camera.model.name, list(camera.params), camera_id, (camera.width, camera.height), str(folder)
        )
    if not out:
        raise InputError("the COLMAP model has no cameras", path=folder)
    return out


def write_model(
    folder: str | Path,
    cameras: list[Camera],
    image_names: list[str],
    image_cameras: np.ndarray,
    keypoints: list[np.ndarray],
    points: np.ndarray,
    tracks: np.ndarray,
) -> None:
    """Write a COLMAP text model (cameras.txt, images.txt, points3D.txt, rigs.txt, frames.txt).

    cameras (C,); image_names (I,) with image_cameras (I,) camera indices; keypoints: I arrays
    (K_i, 2) in OpenCV pixels; points (N, 3) world; tracks (E, 3) rows (point, image,
    keypoint) of the observations of the points, by index.
    """
    import pycolmap

    model = pycolmap.Reconstruction()
    for k, camera in enumerate(cameras):
        name, params = colmap_params(camera)
        model.add_camera_with_trivial_rig(
            pycolmap.Camera(model=name, width=camera.size[0], height=camera.size[1], params=params, camera_id=k + 1)
        )
    for i, (name, c, uv) in enumerate(zip(image_names, image_cameras, keypoints)):
        cam_from_world = cameras[c].cam_from_world
        image = pycolmap.Image(
            name=name, keypoints=np.asarray(uv, dtype=float).reshape(-1, 2) + PIXEL_OFFSET,  # OpenCV -> COLMAP
            camera_id=int(c) + 1, image_id=i + 1,
        )
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_world.rotation), cam_from_world.translation)
        model.add_image_with_trivial_frame(image, pose)
    tracks = np.asarray(tracks, dtype=int).reshape(-1, 3)
    order = np.argsort(tracks[:, 0], kind="stable")
    tracks = tracks[order]
    bounds = np.searchsorted(tracks[:, 0], np.arange(len(points) + 1))
    for n, xyz in enumerate(np.asarray(points, dtype=float)):
        rows = tracks[bounds[n] : bounds[n + 1]]
        track = pycolmap.Track([pycolmap.TrackElement(int(i) + 1, int(kp)) for _, i, kp in rows])
        model.add_point3D(xyz, track)
    model.update_point_3d_errors()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model.write_text(folder)
