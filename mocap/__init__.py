"""mocap: multi-camera motion capture of mining machines, calibrated against the machine itself.

The Python API (mocap.api) is the command line's chain as functions:

    machine = mocap.load_machine("hitachi_ex3500")
    cams = mocap.calibrate(machine, mocap.read_tracks("calibration/labels.csv"), size=(1920, 1080))
    motion = mocap.fit(machine, cams, mocap.read_tracks(["tracks/cam1.csv", "tracks/cam2.csv"]))
    mocap.Session("sessions/day1").run()

Its names are loaded on first use, so `import mocap` (and the command line's start) stays light.
"""

__version__ = "0.1.0"

_API = (
    "Cameras", "Cycles", "InputError", "Motion", "PointsTable", "Refined", "Session", "analyze", "calibrate",
    "concat_tracks", "export", "fit", "load_machine", "motions", "read_calibration", "read_motion", "read_points",
    "read_tracks", "refine", "save_model", "sync", "track", "tracks_to_arrow", "triangulate", "view", "write_tracks",
)

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        import importlib

        value = getattr(importlib.import_module("mocap.api"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'mocap' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
