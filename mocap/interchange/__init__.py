"""Exports to the formats other tools read: C3D and TRC marker files, URDF, COLMAP models."""
