"""The core: the types every stage and every format share and the geometry beside them,
below both. The machine model (machine, its link shapes and visibility, the planar IK),
the camera model (camera, its compiled projection), rigid transforms (geometry), and the
data: tracks, calibration, points, motion, cycles, a calibration guess, a marker table, a
session's fleet summary line, the dig classes, the tag families."""
