"""The Rerun 3-D replay of a dig: machine, markers, cameras with their videos, plots.

`Replay` holds what is shown, `run_replay` records it into an .rrd file and/or a viewer.
"""

from mocap.core.cycles import Cycles
from mocap.io.cycles_csv import load_cycles
from mocap.viewer.replay import Replay, ReplaySummary, Sinks, record_replay, run_replay

__all__ = ["Cycles", "Replay", "ReplaySummary", "Sinks", "load_cycles", "record_replay", "run_replay"]
