"""Camera synchronisation: each camera's time offset from the machine's motion itself
(`align`), and the stage that reads tracks and writes the calibration (`stage`)."""
