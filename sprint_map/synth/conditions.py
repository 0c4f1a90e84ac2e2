"""Appearance conditions of a traversal: light, weather and passing traffic.

A :class:`Condition` is a named preset (``day``, ``overcast``, ``dusk``, ``rain``, ``fog``,
``snow``) whose numbers are jittered per traversal (:meth:`Condition.jittered`), so no two
traversals look exactly alike. :class:`Appearance` applies one to rendered views:

- exposure: per-channel tint, contrast, brightness and gamma (one ``cv2.LUT``);
- fog: blend towards the fog colour by ``1 - exp(-depth / visibility)``, using the view's depth;
- snow cover (the ground turns white, as in Nordland's winter) and falling snow; rain streaks
  and a wet, darker road;
- low sun: a glare blob whose strength depends on the heading relative to the sun, so the same
  street looks different driven one way or the other;
- traffic: vehicles ahead that persist over several frames and partially occlude the view;
- blur and sensor noise.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from sprint_map.synth.render import BGR, View
from sprint_map.util.arrays import Image

__all__ = ["Appearance", "CONDITIONS", "Condition"]


@dataclass(frozen=True)
class Condition:
    """Parameters of one appearance condition (exposure values act on intensities in [0, 1])."""

    name: str
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # B, G, R gains
    contrast: float = 1.0
    brightness: float = 0.0
    gamma: float = 1.0
    sky: tuple[BGR, BGR] = ((235, 200, 150), (250, 235, 215))  # top, horizon
    fog_m: float = 0.0  # visibility (metres); 0: no fog
    fog: BGR = (205, 205, 205)
    snow_cover: float = 0.0  # 0..1 whitening of the ground
    snowfall: float = 0.0  # flakes per 1000 pixels
    rain: float = 0.0  # streaks per 1000 pixels
    wet: float = 0.0  # 0..1 darkening of the ground
    sun_deg: float | None = None  # sun azimuth (CCW from +x) for glare; None: no glare
    glare: float = 0.0  # glare strength looking straight into the sun
    traffic: float = 0.0  # chance per frame that a vehicle appears ahead
    blur: float = 0.0  # Gaussian sigma, pixels
    noise: float = 2.0  # sensor noise sigma, grey levels

    def jittered(self, rng: np.random.Generator) -> Condition:
        """A random variant: every effect strength scaled by ~U(0.75, 1.25), exposure nudged."""

        def scale(value: float) -> float:
            return float(value * rng.uniform(0.75, 1.25))

        return dataclasses.replace(
            self,
            tint=tuple(float(t * rng.uniform(0.95, 1.05)) for t in self.tint),  # type: ignore[arg-type]
            contrast=float(self.contrast * rng.uniform(0.92, 1.08)),
            brightness=float(self.brightness + rng.uniform(-0.04, 0.04)),
            gamma=float(self.gamma * rng.uniform(0.92, 1.08)),
            fog_m=scale(self.fog_m),
            snow_cover=min(1.0, scale(self.snow_cover)),
            snowfall=scale(self.snowfall),
            rain=scale(self.rain),
            wet=min(1.0, scale(self.wet)),
            sun_deg=None if self.sun_deg is None else float(rng.uniform(0, 360)),
            glare=scale(self.glare),
            traffic=scale(self.traffic),
            blur=scale(self.blur),
            noise=scale(self.noise),
        )

    def to_dict(self) -> dict[str, object]:
        """JSON-ready parameters (for the data set's metadata)."""
        return dataclasses.asdict(self)


#: The presets, by name.
CONDITIONS: dict[str, Condition] = {
    c.name: c
    for c in (
        Condition("day", traffic=0.01),
        Condition(
            "overcast",
            tint=(1.02, 1.0, 0.96),
            contrast=0.75,
            brightness=-0.03,
            sky=((200, 198, 195), (215, 215, 212)),
            traffic=0.015,
            noise=3.0,
        ),
        Condition(
            "dusk",
            tint=(0.7, 0.85, 1.1),
            contrast=0.7,
            brightness=-0.18,
            gamma=1.35,
            sky=((150, 110, 120), (110, 170, 245)),
            sun_deg=0.0,
            glare=0.7,
            traffic=0.015,
            noise=6.0,
        ),
        Condition(
            "rain",
            tint=(1.03, 1.0, 0.95),
            contrast=0.7,
            brightness=-0.08,
            sky=((170, 168, 165), (190, 190, 188)),
            rain=6.0,
            wet=0.35,
            fog_m=250.0,
            fog=(180, 180, 178),
            traffic=0.02,
            blur=0.7,
            noise=4.0,
        ),
        Condition(
            "fog",
            contrast=0.9,
            sky=((205, 205, 205), (210, 210, 210)),
            fog_m=70.0,
            traffic=0.01,
            noise=3.0,
        ),
        Condition(
            "snow",
            tint=(1.06, 1.0, 0.96),
            contrast=0.8,
            brightness=0.04,
            sky=((215, 212, 210), (230, 230, 228)),
            snow_cover=0.75,
            snowfall=5.0,
            fog_m=180.0,
            fog=(225, 225, 225),
            traffic=0.01,
            blur=0.4,
            noise=3.0,
        ),
    )
}


@dataclass
class _Vehicle:
    x: float  # centre, fraction of image width
    scale: float  # height as a fraction of image height
    growth: float  # scale change per frame (approaching > 1, leaving < 1)
    life: int
    colour: BGR


class Appearance:
    """Applies one condition to consecutive views of a traversal (it keeps the traffic state).

    Parameters
    ----------
    condition : Condition
    rng : numpy.random.Generator
        Per-traversal generator; frames must be processed in order for determinism.
    """

    def __init__(self, condition: Condition, rng: np.random.Generator) -> None:
        self.condition = condition
        self.rng = rng
        self._lut = _exposure_lut(condition)
        self._vehicles: list[_Vehicle] = []
        self._noise_bank: np.ndarray | None = None

    def apply(self, view: View, heading_deg: float) -> Image:
        """Return the view's image under this condition (uint8 BGR, same size)."""
        c = self.condition
        out: Image = view.image.copy()  # the drawing below works in place
        glare = 0.0
        if c.glare and c.sun_deg is not None:
            glare = c.glare * max(0.0, float(np.cos(np.radians(heading_deg - c.sun_deg)))) ** 3
        if c.snow_cover or c.wet or c.fog_m or glare:
            out = self._light(view, glare)
        self._traffic(out)
        if c.rain:
            self._streaks(out, c.rain)
        if c.snowfall:
            self._flakes(out, c.snowfall)
        out = cv2.LUT(out, self._lut)
        if c.blur > 0.05:
            out = cv2.GaussianBlur(out, (0, 0), c.blur)
        if c.noise > 0:
            noisy = out + self._noise(out.shape)
            out = np.clip(noisy, 0, 255, out=noisy).astype(np.uint8)
        return out

    def _noise(self, shape: tuple[int, ...]) -> np.ndarray:
        """A sensor-noise field: a random window of one of a few pre-drawn fields.

        Drawing 57,600 normals per 160x120 frame costs ~1 ms, a quarter of the frame time;
        8 fields x (33 x 33) offsets look just as random to a descriptor.
        """
        h, w = shape[:2]
        if self._noise_bank is None or self._noise_bank.shape[1:3] != (h + 32, w + 32):
            field = self.rng.standard_normal((8, h + 32, w + 32, *shape[2:]), dtype=np.float32)
            self._noise_bank = field * np.float32(self.condition.noise)
        k, dy, dx = self.rng.integers(0, (8, 33, 33))
        return self._noise_bank[k, dy : dy + h, dx : dx + w]

    def _light(self, view: View, glare: float) -> np.ndarray:
        """Snow cover, wet road, fog and glare: blends that need float intensities."""
        c = self.condition
        img = view.image.astype(np.float32)
        h, w = img.shape[:2]
        ground = view.ground[:, :, None]
        if c.snow_cover:
            img += (ground * c.snow_cover) * (245.0 - img)
        if c.wet:
            img *= 1.0 - c.wet * ground
        if c.fog_m:
            weight = (1.0 - np.exp(-view.depth / c.fog_m))[:, :, None]
            img += weight * (np.array(c.fog, dtype=np.float32) - img)
        if glare:
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            blob = np.exp(-((xx - w * 0.5) ** 2 + (yy - h * 0.35) ** 2) / (0.18 * w * w))
            img += (glare * 255.0) * blob[:, :, None]
        return np.clip(img, 0, 255, out=img).astype(np.uint8)

    def _traffic(self, img: np.ndarray) -> None:
        h, w = img.shape[:2]
        rng = self.rng
        if rng.random() < self.condition.traffic:
            shade = int(rng.integers(20, 230))
            tint = rng.integers(-30, 31, size=3)
            colour = tuple(int(np.clip(shade + t, 0, 255)) for t in tint)
            self._vehicles.append(
                _Vehicle(
                    x=float(rng.uniform(0.25, 0.75)),
                    scale=float(rng.uniform(0.1, 0.25)),
                    growth=float(rng.uniform(0.97, 1.04)),
                    life=int(rng.integers(6, 20)),
                    colour=(colour[0], colour[1], colour[2]),
                )
            )
        alive = []
        for v in self._vehicles:
            vh = v.scale * h
            vw = 1.6 * vh
            cx, bottom = v.x * w, h * 0.5 + vh * 0.8  # standing on the road below the horizon
            x0, x1, y0 = cx - vw / 2, cx + vw / 2, bottom - vh
            cv2.rectangle(img, (round(x0), round(y0)), (round(x1), round(bottom)), v.colour, -1)
            window = (round(x0 + vw * 0.12), round(y0 + vh * 0.1))
            cv2.rectangle(
                img, window, (round(x1 - vw * 0.12), round(y0 + vh * 0.4)), (40, 35, 30), -1
            )
            for lx in (x0 + vw * 0.12, x1 - vw * 0.12):  # rear lights
                cv2.circle(
                    img,
                    (round(lx), round(y0 + vh * 0.6)),
                    max(1, round(vh * 0.07)),
                    (30, 30, 200),
                    -1,
                )
            v.scale *= v.growth
            v.life -= 1
            if v.life > 0 and 0.05 < v.scale < 0.6:
                alive.append(v)
        self._vehicles = alive

    def _streaks(self, img: np.ndarray, density: float) -> None:
        h, w = img.shape[:2]
        n = self.rng.poisson(density * h * w / 1000)
        x = self.rng.uniform(0, w, n)
        y = self.rng.uniform(0, h, n)
        length = self.rng.uniform(4, 10, n)
        overlay = img.copy()
        for xi, yi, li in zip(x, y, length, strict=True):
            cv2.line(
                overlay,
                (round(xi), round(yi)),
                (round(xi + 0.25 * li), round(yi + li)),
                (200, 200, 200),
                1,
            )
        cv2.addWeighted(overlay, 0.45, img, 0.55, 0, dst=img)

    def _flakes(self, img: np.ndarray, density: float) -> None:
        h, w = img.shape[:2]
        n = self.rng.poisson(density * h * w / 1000)
        for xi, yi, r in zip(
            self.rng.uniform(0, w, n),
            self.rng.uniform(0, h, n),
            self.rng.integers(0, 2, n),
            strict=True,
        ):
            cv2.circle(img, (round(xi), round(yi)), int(r), (250, 250, 250), -1)


def _exposure_lut(c: Condition) -> np.ndarray:
    """Per-channel 256-entry table: tint, then contrast about mid-grey, brightness, gamma."""
    levels = np.arange(256, dtype=np.float64) / 255.0
    channels = []
    for gain in c.tint:
        x = np.clip(c.contrast * (levels * gain - 0.5) + 0.5 + c.brightness, 0, 1)
        channels.append(np.round(255.0 * x**c.gamma))
    return np.stack(channels, axis=1).astype(np.uint8).reshape(256, 1, 3)
