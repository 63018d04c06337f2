"""Markers' disk normals learned from the ellipses the disks show, for a model that states none.

A disk of radius r whose centre lies at C in the camera frame, seen along d = C / |C|, shows
(to first order in r / |C|) as the image of an ellipse in the plane square to d: its major
semi-axis r, its minor r cos(theta), the minor one along the normal's lean out of d. The image
ellipse (semi-axis matrix S, px²) is taken back to that plane by the inverse of the Jacobian J
of the projection there (lens distortion included): S' = J⁻¹ S J⁻ᵀ. Its axes give cos(theta) =
b / a and the lean's direction w, and so the normal facing the camera up to a two-fold
ambiguity, n = -cos(theta) d ± sin(theta) w. In the marker's link frame the true normal stays
put while the other moves as the link turns against the camera: over frames (and cameras)
the candidate most of the others agree with is the normal (`learn_normals`).

The learned normals are a prior like the boxes' guess (what the model expects to see, how
large), never a veto: the tracker labels a disk the fit agrees with whatever they say.

Shapes: N observations, M markers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.camera import project_cam

MIN_AXIS_PX = 2.5  # a disk whose major semi-axis is smaller says little of its turn
AGREE_DEG = 6.0  # candidates within this of each other agree
MIN_SEEN = 8  # observations a marker needs for a learned normal
KEEP_PER_MARKER = 120  # observations a learner holds per marker: between this and twice it
PROPOSALS = 40  # observations whose candidates are scored as the normal (spread over all)


@dataclass(frozen=True)
class LearnedNormals:
    """Per marker (M,): `normals` (M, 3) unit, in its link frame (NaN: not learned),
    `spread_deg` the agreeing candidates' RMS angle from it, `seen` the observations
    used, `resolved` whether the two-fold ambiguity was settled by the data (False: both
    fit as well, the one nearer the prior taken)."""

    normals: np.ndarray
    spread_deg: np.ndarray
    seen: np.ndarray
    resolved: np.ndarray

    @property
    def learned(self) -> np.ndarray:
        """(M,) bool: a normal was learned."""
        return np.all(np.isfinite(self.normals), axis=1)


def normal_candidates(shape: np.ndarray, centre_cam: np.ndarray, matrix: np.ndarray,
                      distortion: np.ndarray) -> np.ndarray:
    """(N, 2, 3) the two unit normals facing the camera, in the camera frame, that disks whose
    centres lie at `centre_cam` (N, 3) show as image ellipses of semi-axis matrices `shape`
    (N, 2, 2) px² (R diag(a², b²) Rᵀ); NaN where a centre is behind the camera."""
    centre_cam = np.asarray(centre_cam, dtype=float)
    d = centre_cam / np.linalg.norm(centre_cam, axis=-1, keepdims=True)
    helper = np.where(np.abs(d[:, :1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(d, e1)
    _, jacobian = project_cam(centre_cam, matrix, distortion, with_jacobian=True)  # (N, 2, 3)
    plane = np.stack([e1, e2], axis=-1)  # (N, 3, 2)
    j = jacobian @ plane  # (N, 2, 2): pixels per metre along e1, e2
    inverse = np.linalg.inv(np.where(np.isfinite(j), j, np.eye(2)))
    on_plane = inverse @ shape @ np.swapaxes(inverse, -1, -2)
    values, vectors = np.linalg.eigh(on_plane)  # ascending: the minor axis first
    cos = np.sqrt(np.clip(values[:, 0], 0.0, None) / np.maximum(values[:, 1], 1e-300))
    sin = np.sqrt(np.clip(1.0 - cos**2, 0.0, None))
    lean = np.einsum("nij,nj->ni", plane, vectors[:, :, 0])  # (N, 3) the minor axis in 3-D
    signs = np.array([1.0, -1.0])[None, :, None]
    candidates = -cos[:, None, None] * d[:, None] + signs * sin[:, None, None] * lean[:, None]
    return np.where(np.all(np.isfinite(j), axis=(1, 2))[:, None, None] & (centre_cam[:, None, 2:] > 0), candidates,
                    np.nan)


@dataclass(frozen=True)
class NormalEvidence:
    """The candidate normal pairs (N, 2, 3) of N labelled disks, in their links' frames, and
    the `markers` (N,) whose; of a machine of `n_markers`. Cameras' evidence pools
    (`pooled`): the candidates are in the links' frames."""

    markers: np.ndarray
    candidates: np.ndarray
    n_markers: int

    def learn(self, prior: np.ndarray | None = None, min_seen: int = MIN_SEEN) -> LearnedNormals:
        """The normals learned from the evidence (`learn_normals`)."""
        return learn_normals(self.markers, self.candidates, self.n_markers, prior, min_seen)

    @staticmethod
    def pooled(evidence: list[NormalEvidence]) -> NormalEvidence:
        """Several cameras' (or clips') evidence of the same machine as one."""
        return NormalEvidence(np.concatenate([e.markers for e in evidence]),
                              np.concatenate([e.candidates for e in evidence]), evidence[0].n_markers)


class NormalLearner:
    """Collects the candidate normals of labelled disks, frame by frame (`add`), as
    `NormalEvidence`: at most 2 x `keep` observations per marker, spread over the whole run
    (when a marker has more, every other one is let go), so that a run of hours holds as
    little as a minute's and learning costs the same."""

    def __init__(self, n_markers: int, min_axis_px: float = MIN_AXIS_PX, keep: int = KEEP_PER_MARKER):
        self.n_markers = n_markers
        self.min_axis_px = min_axis_px
        self.keep = keep
        self._candidates: list[list[np.ndarray]] = [[] for _ in range(n_markers)]

    def add(self, markers: np.ndarray, axes: np.ndarray, shape: np.ndarray, centre_cam: np.ndarray,
            cam_from_link: np.ndarray, matrix: np.ndarray, distortion: np.ndarray) -> None:
        """One frame's labelled disks: `markers` (K,) indices, their ellipses' `axes` (K, 2)
        and semi-axis matrices `shape` (K, 2, 2) px², their centres `centre_cam` (K, 3) and
        their links' rotations `cam_from_link` (K, 3, 3) by the fitted model."""
        keep = axes[:, 0] >= self.min_axis_px
        if not np.any(keep):
            return
        in_cam = normal_candidates(shape[keep], centre_cam[keep], matrix, distortion)
        in_link = np.einsum("kji,kcj->kci", cam_from_link[keep], in_cam)  # link_from_cam = transpose
        for m, pair in zip(np.asarray(markers)[keep], in_link):
            if np.all(np.isfinite(pair)):
                held = self._candidates[m]
                held.append(pair)
                if len(held) > 2 * self.keep:
                    del held[1::2]

    def evidence(self) -> NormalEvidence:
        """What was collected so far."""
        counts = [len(c) for c in self._candidates]
        markers = np.repeat(np.arange(self.n_markers), counts)
        candidates = np.array([p for c in self._candidates for p in c]).reshape(-1, 2, 3)
        return NormalEvidence(markers, candidates, self.n_markers)


def learn_normals(markers: np.ndarray, candidates: np.ndarray, n_markers: int, prior: np.ndarray | None = None,
                  min_seen: int = MIN_SEEN, agree_deg: float = AGREE_DEG) -> LearnedNormals:
    """Each marker's normal from its observations' candidate pairs `candidates` (N, 2, 3) in
    its link frame, `markers` (N,) whose: the candidate that the most observations have a
    candidate within `agree_deg` of (each observation counts once), refined as the mean of
    those agreeing candidates. Resolved when the mirror cluster (the best-supported candidate more
    than 2 x `agree_deg` away) has under two thirds of its support (the mirrors moved as the
    link turned against the camera); else the one of the two nearer
    `prior` (M, 3) where given."""
    normals = np.full((n_markers, 3), np.nan)
    spread = np.full(n_markers, np.nan)
    seen = np.bincount(np.asarray(markers, dtype=int), minlength=n_markers)[:n_markers]
    resolved = np.zeros(n_markers, dtype=bool)
    cos_agree = np.cos(np.radians(agree_deg))
    for m in np.flatnonzero(seen >= min_seen):
        pairs = candidates[markers == m]  # (K, 2, 3)
        # the candidates of up to PROPOSALS observations spread over them, each scored by its
        # support: the observations with a candidate within agree_deg of it
        flat = pairs[np.unique(np.linspace(0, len(pairs) - 1, PROPOSALS).astype(int))].reshape(-1, 3)
        dots = (pairs.reshape(-1, 3) @ flat.T).reshape(len(pairs), 2, len(flat))  # (K, 2, P)
        support = np.sum(dots.max(axis=1) > cos_agree, axis=0)
        order = np.argsort(-support)
        best = flat[order[0]]
        far = flat[order] @ best < np.cos(np.radians(2 * agree_deg))
        rival = flat[order][far][0] if np.any(far) else None
        rival_support = support[order][far][0] if np.any(far) else 0
        chosen, is_resolved = best, rival_support < (2 / 3) * support[order[0]]
        if not is_resolved and prior is not None and rival is not None and np.all(np.isfinite(prior[m])):
            refined = [_refine(pairs, c, cos_agree) for c in (best, rival)]
            chosen = refined[int(np.argmax([r[0] @ prior[m] for r in refined]))][0]
        normal, angles = _refine(pairs, chosen, cos_agree)
        normals[m], spread[m], resolved[m] = normal, np.sqrt(np.mean(angles**2)), is_resolved
    return LearnedNormals(normals, spread, seen, resolved)


def _refine(pairs: np.ndarray, around: np.ndarray, cos_agree: float, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """The mean (unit) of each observation's candidate nearest `around` among those within
    the agreement angle, recentred a few times; and their angles (deg) from it."""
    normal = around
    for _ in range(rounds):
        dots = pairs @ normal  # (K, 2)
        nearest = pairs[np.arange(len(pairs)), np.argmax(dots, axis=1)]
        near = nearest[np.max(dots, axis=1) > cos_agree]
        if len(near) == 0:
            break
        mean = near.mean(axis=0)
        normal = mean / np.linalg.norm(mean)
    dots = np.clip(pairs @ normal, -1.0, 1.0).max(axis=1)
    return normal, np.degrees(np.arccos(dots[dots > cos_agree]))
