"""How a synthetic session looks: machine paint, light, marker paint, weather and camera,
so that tracking is measured over many looks rather than the one it was tuned on.

`Look()` is the renderer's default look; `random_look(rng)` draws one of many: yellow,
white, orange or mud-covered machines; high or low sun from any side, or overcast; disks
of 45-75 % of their square, worn (greyer white, lighter black), dark grey instead of black,
or painted straight on the machine without a white square; haze; slight defocus; heavy or
light compression; more or less sensor noise, exposure drift and dust; lens distortion and
camera shake; a rolling shutter (or a global one); rain streaks; a low sun's glare; the
links' hard shadows on each other; haul trucks, another machine and people behind the
machine. The look is written into truth/scene.toml.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

PAINTS = {  # BGR of the house, boom and arm
    "orange": (25.0, 125.0, 240.0),
    "yellow": (30.0, 190.0, 235.0),
    "white": (215.0, 218.0, 220.0),
    "mud": (70.0, 95.0, 115.0),
    "red": (40.0, 45.0, 190.0),
}
HAZE = np.array([225.0, 222.0, 215.0])  # BGR


@dataclass(frozen=True)
class Look:
    """One look of a rendered session (grey levels 0-255, BGR colours, degrees, pixels).

    paint: colour of the house, boom and arm; dark: of the undercarriage and bucket;
    sun_elevation_deg / sun_azimuth_deg: the sun (None: drawn per camera, 35-60° high);
    overcast: 0 hard sunlight to 1 flat light; disk_ratio: the disk's diameter over its
    square's side; disk_grey, square_grey: the paint (18 and 235 new; None square: the
    disk painted straight on the machine, but on dark links, where it would not show);
    haze: share of haze over the whole picture;
    defocus: Gaussian blur SD px; noise, exposure, dust, blur: the camera effects
    (`EffectOptions`); crf: H.264 quality (23 default, 35 heavy compression); scale: the
    image size's factor; distortion, shake_deg: the lens and the camera's wind shake;
    rain: the rain streaks' opacity, glare: a low sun's veiling glare
    (`mocap.synthetic.effects.Weather`); people, trucks, other_machine: clutter behind the
    machine: people in high-visibility vests, haul trucks with their tyres, another machine
    with a sign on it (`mocap.synthetic.backdrop`); shadows: the links' hard shadows on each
    other's sunlit faces and markers (`mocap.synthetic.render`); readout: the rolling
    shutter, the rows read one after another over that share of the frame interval (0: a
    global shutter; the session's truth follows it: `SessionOptions.readout`).
    """

    name: str = "default"
    paint: tuple[float, float, float] = PAINTS["orange"]
    dark: tuple[float, float, float] = (72.0, 75.0, 80.0)
    sun_elevation_deg: float | None = None
    sun_azimuth_deg: float | None = None
    overcast: float = 0.0
    disk_ratio: float = 0.6
    disk_grey: float = 18.0
    square_grey: float | None = 235.0
    haze: float = 0.0
    defocus: float = 0.0
    noise: float = 2.5
    exposure: float = 0.08
    dust: float = 0.55
    blur: float = 0.5
    crf: int = 23
    scale: float = 1.0
    distortion: bool = False
    shake_deg: float = 0.0
    rain: float = 0.0
    glare: float = 0.0
    people: int = 0
    trucks: int = 0
    other_machine: bool = False
    shadows: bool = False
    readout: float = 0.0

    def __post_init__(self) -> None:
        if not 0.2 <= self.disk_ratio <= 0.9:
            raise ValueError(f"disk_ratio must be 0.2..0.9, got {self.disk_ratio}")
        if not (0 <= self.overcast <= 1 and 0 <= self.haze <= 0.8 and self.defocus >= 0):
            raise ValueError("overcast must be 0..1, haze 0..0.8, defocus >= 0")
        if not (0 <= self.rain <= 1 and 0 <= self.glare <= 0.6 and self.people >= 0 and self.trucks >= 0):
            raise ValueError("rain must be 0..1, glare 0..0.6, people and trucks >= 0")
        if not 0 <= self.crf <= 51:
            raise ValueError(f"crf must be 0..51, got {self.crf}")
        if not 0 <= self.readout <= 0.9:
            raise ValueError(f"readout must be 0..0.9 of the frame interval, got {self.readout}")

    @property
    def palette(self) -> np.ndarray:
        """(5, 3) BGR link colours, repeated over the links: undercarriage, house, boom, arm, bucket."""
        paint = np.asarray(self.paint, dtype=float)
        return np.array([self.dark, paint, paint * 1.04, paint * 0.96, self.dark]).clip(0, 255)

    def sun(self) -> np.ndarray | None:
        """The unit vector towards the sun (world), or None to draw one per camera."""
        if self.sun_elevation_deg is None or self.sun_azimuth_deg is None:
            return None
        e, a = np.radians(self.sun_elevation_deg), np.radians(self.sun_azimuth_deg)
        return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

    def shade(self, facing_sun: float) -> float:
        """A face's brightness factor from the cosine of its angle to the sun."""
        sunlit = 0.45 + 0.55 * max(0.0, facing_sun)
        return (1.0 - self.overcast) * sunlit + self.overcast * 0.75

    def finish(self, image: np.ndarray) -> np.ndarray:
        """The optics on a clean picture (H, W, 3) uint8: haze over everything, then defocus."""
        if self.haze > 0:
            haze = np.empty_like(image)
            haze[:] = HAZE.astype(np.uint8)
            image = cv2.addWeighted(image, 1.0 - self.haze, haze, self.haze, 0.0)
        if self.defocus > 0:
            image = cv2.GaussianBlur(image, (0, 0), self.defocus)
        return image

    def table(self) -> dict:
        """The look as a TOML table (None values left out)."""
        out = {}
        for key, value in asdict(self).items():
            if value is None:
                continue
            out[key] = [float(v) for v in value] if isinstance(value, tuple) else value
        return out


def random_look(rng: np.random.Generator, name: str = "random") -> Look:
    """A look drawn at random (see the module's docstring)."""
    paint = str(rng.choice(list(PAINTS)))
    overcast = float(rng.choice([0.0, 0.0, 0.3, 1.0]))
    marker = rng.choice(["new", "worn", "grey disk", "no square"], p=[0.35, 0.25, 0.2, 0.2])
    disk_grey, square_grey = 18.0, 235.0
    if marker == "worn":
        disk_grey, square_grey = rng.uniform(35, 60), rng.uniform(180, 215)
    elif marker == "grey disk":
        disk_grey = rng.uniform(60, 85)
    elif marker == "no square":
        square_grey = None
    look = Look(
        name=f"{name} ({paint}, {'overcast' if overcast == 1 else 'sun'}, {marker} markers)",
        paint=PAINTS[paint],
        dark=tuple(float(v) for v in rng.uniform(45, 90) * np.array([1.0, 1.03, 1.08])),
        sun_elevation_deg=float(rng.uniform(8, 75)),
        sun_azimuth_deg=float(rng.uniform(0, 360)),
        overcast=overcast,
        disk_ratio=float(rng.uniform(0.45, 0.75)),
        disk_grey=float(disk_grey),
        square_grey=None if square_grey is None else float(square_grey),
        haze=float(rng.choice([0.0, 0.0, rng.uniform(0.1, 0.35)])),
        defocus=float(rng.choice([0.0, rng.uniform(0.4, 1.2)])),
        noise=float(rng.uniform(1.0, 5.0)),
        exposure=float(rng.uniform(0.0, 0.15)),
        dust=float(rng.uniform(0.2, 0.8)),
        blur=float(rng.uniform(0.2, 0.7)),
        crf=int(rng.choice([18, 23, 28, 33])),
        scale=float(rng.choice([2 / 3, 1.0, 4 / 3])),
        distortion=bool(rng.random() < 0.5),
        shake_deg=float(rng.choice([0.0, rng.uniform(0.01, 0.05)])),
        rain=float(rng.uniform(0.15, 0.45)) if rng.random() < 0.3 else 0.0,
        glare=float(rng.uniform(0.15, 0.4)) if rng.random() < 0.3 else 0.0,
        people=int(rng.integers(1, 6)) if rng.random() < 0.5 else 0,
        trucks=int(rng.integers(1, 3)) if rng.random() < 0.5 else 0,
        other_machine=bool(rng.random() < 0.4),
        shadows=bool(rng.random() < 0.6),
    )
    readout = float(rng.uniform(0.2, 0.9)) if rng.random() < 2 / 3 else 0.0  # drawn last: the rest as before
    people = f"{look.people} {'person' if look.people == 1 else 'people'}"
    trucks = f"{look.trucks} truck{'s' if look.trucks > 1 else ''}"
    extras = [word for word, on in (("rain", look.rain), ("glare", look.glare), (people, look.people),
                                    (trucks, look.trucks), ("another machine", look.other_machine),
                                    ("shadows", look.shadows and overcast < 1),
                                    (f"rolling shutter {readout:.2f}", readout)) if on]
    return replace(look, name=look.name[:-1] + "".join(f", {word}" for word in extras) + ")", readout=readout)
