"""Core types that the formats (mocap.io) read and write and the stages compute with,
below both: a calibration guess, a marker table, a session's fleet summary line."""
