"""Command-line sub-commands: each module wires arguments to one stage.

`COMMANDS` is the table of sub-commands and their one-line help; `mocap.cli` (the entry
point, imported by no other module) builds its parser from it and imports a command's
module only when that command runs.
"""

COMMANDS = {  # name: one line of help; each command's module is imported only when it runs
    "calibrate": "calibrate cameras against the machine's markers in one frame",
    "view": "record the 3-D replay of a dig in Rerun",
    "synth": "write a synthetic session (videos and truth) of a machine digging",
    "track": "detect, label and track the machine's markers in one camera's video",
    "sync": "estimate each camera's time offset from the machine's motion",
    "triangulate": "triangulate every marker in every frame seen by two or more cameras",
    "fit": "fit the machine model to all cameras' marker pixels in every frame",
    "analyze": "dig cycles, phases, classes, similarity and templates from the motion",
    "refine": "refine cameras (and marker positions) over many frames",
    "run": "run the whole chain on a session folder",
    "batch": "run every session under the paths through the chain on Dask, skip what is up to date",
    "export": "write markers (C3D, TRC), a machine model (URDF) or a session (COLMAP) for other tools",
    "demo": "make a synthetic session, run the whole chain and score it against the truth",
    "report": "the session report: calibration, tracking, sync and fit quality, and what to fix first",
    "live": "the machine's pose frame by frame from cameras as they deliver (files, devices, streams)",
}
