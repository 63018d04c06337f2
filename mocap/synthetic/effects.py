"""What a field camera adds to a clean picture: exposure drift, dust, noise; and how long
its shutter stays open (`blur`), which the renderer turns into the smear of moving parts
(`mocap.synthetic.render`).

Each effect is cheap per frame at 1080p: dust is a soft plume blended into a small region
around the bucket while it digs, and the exposure's gain and the sensor noise (from a bank
of noise images drawn once) are one saturating pass over the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mocap.synthetic.paths import SmoothNoise

DUST = np.array([150.0, 170.0, 185.0])  # BGR


@dataclass(frozen=True)
class EffectOptions:
    """Strengths of the effects; 0 turns one off. `noise` is the sensor noise SD (grey
    levels), `blur` the exposure as a share of the frame interval (motion blur), `exposure`
    the SD of the gain's drift, `dust` the densest plume's opacity."""

    noise: float = 2.5
    blur: float = 0.5
    exposure: float = 0.08
    dust: float = 0.55

    def __post_init__(self) -> None:
        for name in ("noise", "blur", "exposure", "dust"):
            value = getattr(self, name)
            if not 0.0 <= value <= (0.9 if name in ("blur", "dust") else 50.0):
                raise ValueError(f"effect {name!r} out of range: {value}")

    @classmethod
    def none(cls) -> EffectOptions:
        return cls(0.0, 0.0, 0.0, 0.0)


class CameraEffects:
    """Per-camera effect state: the noise bank, the gain's drift, the dust plume's shape."""

    def __init__(self, size: tuple[int, int], options: EffectOptions, rng: np.random.Generator):
        w, h = size
        self.options = options
        self.rng = rng
        self.bank = []  # noise images offset by 128, added with one saturating pass
        if options.noise > 0:
            for _ in range(4):
                noise = rng.normal(128.0, options.noise, (h, w, 3))
                self.bank.append(np.clip(np.round(noise), 0, 255).astype(np.uint8))
        self.gain = SmoothNoise.random(rng, np.array([options.exposure]), (0.01, 0.08), k=4)
        yy, xx = np.mgrid[-1:1:96j, -1:1:96j]
        lumps = cv2.GaussianBlur(rng.uniform(0, 1, (96, 96)).astype(np.float32), (0, 0), 6)
        lumps = (lumps - lumps.min()) / max(np.ptp(lumps), 1e-6)
        self.plume = (np.clip(1 - (xx**2 + yy**2), 0, 1) ** 1.5 * (0.5 + 0.5 * lumps)).astype(np.float32)

    def apply(self, image: np.ndarray, time: float, dust_centre: np.ndarray | None, dust_radius: float,
              dust_density: float) -> np.ndarray:
        """The camera's picture of the clean `image` (H, W, 3) uint8 at `time` s, changed in
        place: the dust plume (radius px) around `dust_centre` (2,) px with a density in
        [0, 1], the exposure's gain, the sensor noise."""
        if self.options.dust > 0 and dust_centre is not None and dust_density > 0 and np.all(np.isfinite(dust_centre)):
            self._dust(image, dust_centre, dust_radius, dust_density)
        gain = 1.0 + float(self.gain(np.array([time]))[0, 0]) if self.options.exposure > 0 else 1.0
        if self.bank:
            noise = self.bank[int(self.rng.integers(len(self.bank)))]
            return cv2.addWeighted(image, gain, noise, 1.0, -128.0)
        if gain != 1.0:
            return cv2.convertScaleAbs(image, alpha=gain)
        return image

    def _dust(self, image: np.ndarray, centre: np.ndarray, radius: float, density: float) -> None:
        h, w = image.shape[:2]
        r = int(max(4, radius))
        x0, y0 = int(centre[0]) - r, int(centre[1]) - r
        xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + 2 * r, w), min(y0 + 2 * r, h)
        if xb <= xa or yb <= ya:
            return
        alpha = cv2.resize(self.plume, (2 * r, 2 * r))[ya - y0 : yb - y0, xa - x0 : xb - x0]
        alpha = np.ascontiguousarray(alpha * (self.options.dust * density), dtype=np.float32)
        roi = image[ya:yb, xa:xb]
        colour = np.empty_like(roi)
        colour[:] = DUST.astype(np.uint8)
        image[ya:yb, xa:xb] = cv2.blendLinear(roi, colour, 1.0 - alpha, alpha)


class Weather:
    """Rain streaks and a low sun's glare over a camera's picture, drawn once per camera.

    Rain: a bank of layers of thin slanted light streaks (all falling the same way), one
    layer a frame, added with one saturating pass; `rain` is a streak's opacity (0: none).
    Glare: the sun just above the picture's top edge, a veil of light over the whole
    picture growing towards it and two faint ghost disks on the line from it through the
    picture's centre, each blended towards white; `glare` scales the veil's share: a quarter
    of it far from the sun, one and a half times it by the sun (at most 0.9; 0: none)."""

    def __init__(self, size: tuple[int, int], rain: float, glare: float, rng: np.random.Generator):
        w, h = size
        self.bank: list[np.ndarray] = []
        if rain > 0:
            slant = rng.uniform(-0.35, 0.35)  # dx per dy
            count = int(rng.uniform(2e-4, 6e-4) * w * h)
            for _ in range(4):
                layer = np.zeros((h, w), np.float32)
                x, y = rng.uniform(-0.2 * w, 1.2 * w, count), rng.uniform(0, h, count)
                length = rng.uniform(0.02, 0.06, count) * h
                ends = np.stack([x, y, x + slant * length, y + length], axis=1)
                for x0, y0, x1, y1 in np.round(ends * 16).astype(np.int32):
                    cv2.line(layer, (x0, y0), (x1, y1), 1.0, 1, cv2.LINE_AA, shift=4)
                layer = cv2.GaussianBlur(layer, (0, 0), 0.6) * (255.0 * rain)
                self.bank.append(np.clip(layer, 0, 255).astype(np.uint8)[..., None].repeat(3, axis=2))
        self.veil = None
        if glare > 0:
            sun = np.array([rng.uniform(0.1, 0.9) * w, -rng.uniform(0.02, 0.15) * h])
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            r = np.hypot(xx - sun[0], yy - sun[1]) / np.hypot(w, h)
            veil = 0.25 + 0.75 * np.exp(-((r / 0.25) ** 2)) + 0.5 * np.exp(-((r / 0.06) ** 2))
            for share, radius, opacity in ((0.6, 0.05, 0.25), (1.4, 0.09, 0.15)):
                ghost = sun + share * (np.array([w / 2, h / 2]) - sun) * 2
                g = np.hypot(xx - ghost[0], yy - ghost[1]) / np.hypot(w, h)
                veil += opacity * np.clip((radius - g) / 0.01, 0, 1)
            self.veil = np.clip(veil * glare, 0, 0.9).astype(np.float32)
            self.white = np.full((h, w, 3), 250, np.uint8)

    def apply(self, image: np.ndarray, frame: int) -> np.ndarray:
        """The picture (H, W, 3) uint8 with the glare's veil and frame `frame`'s rain added."""
        if self.veil is not None:  # scattered light over the picture: lifts the darks, flattens contrast
            image = cv2.blendLinear(image, self.white, 1.0 - self.veil, self.veil)
        if self.bank:
            image = cv2.add(image, self.bank[frame % len(self.bank)])
        return image
