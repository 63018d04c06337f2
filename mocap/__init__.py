"""mocap: multi-camera motion capture of mining machines, calibrated against the machine itself."""

__version__ = "0.1.0"
