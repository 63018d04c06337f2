"""3-D reconstruction: triangulation of markers, the batched kinematic fit, temporal
smoothing with gap filling, uncertainty propagation and model refinement."""
