"""Procedural textures for the synthetic city, drawn with OpenCV: facades, ground, skyline.

Facades are drawn from a :class:`FacadeStyle` (colours, window grid, ground-floor shop, wall
pattern) plus per-building *details* (posters, graffiti, signs, poles, trees, air conditioners).
Streets whose buildings share a style look alike and differ only in details: that is the
perceptual aliasing that makes single-frame place recognition imperfect. Texture row 0 is the top
of the building; one texel is ``1 / px_per_m`` metres.
"""

from __future__ import annotations

import string
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["BGR", "FacadeStyle", "PATTERNS", "draw_facade", "draw_skyline", "random_style"]

BGR = tuple[int, int, int]

PATTERNS = ("plain", "brick", "panels", "stripes")


@dataclass(frozen=True)
class FacadeStyle:
    """Appearance shared by the buildings of one style (one or more street sides)."""

    wall: BGR
    pattern: str
    noise: float  # std of per-texel wall noise (grey levels)
    floor_m: float  # storey height
    window_w_m: float
    window_h_m: float
    window_pitch_m: float  # horizontal distance between window centres
    glass: BGR
    frame: BGR
    shop: bool  # ground floor is a shop front with awning and sign
    awning: BGR
    cornice: bool
    balconies: bool


def _colour(rng: np.random.Generator, low: int, high: int) -> BGR:
    b, g, r = (int(v) for v in rng.integers(low, high, size=3))
    return b, g, r


def random_style(rng: np.random.Generator) -> FacadeStyle:
    """Draw a facade style."""
    base = int(rng.integers(70, 210))
    tint = rng.integers(-35, 36, size=3)
    wall = tuple(int(np.clip(base + t, 20, 235)) for t in tint)
    return FacadeStyle(
        wall=(wall[0], wall[1], wall[2]),
        pattern=str(rng.choice(PATTERNS)),
        noise=float(rng.uniform(3, 14)),
        floor_m=float(rng.uniform(2.9, 4.0)),
        window_w_m=float(rng.uniform(0.8, 2.2)),
        window_h_m=float(rng.uniform(1.2, 2.0)),
        window_pitch_m=float(rng.uniform(2.2, 4.0)),
        glass=_colour(rng, 20, 110),
        frame=_colour(rng, 150, 250) if rng.random() < 0.6 else _colour(rng, 10, 70),
        shop=bool(rng.random() < 0.6),
        awning=_colour(rng, 30, 230),
        cornice=bool(rng.random() < 0.5),
        balconies=bool(rng.random() < 0.35),
    )


def _vary(colour: BGR, rng: np.random.Generator, amount: int) -> BGR:
    b, g, r = (int(np.clip(c + rng.integers(-amount, amount + 1), 0, 255)) for c in colour)
    return b, g, r


def _rect(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, colour: BGR) -> None:
    cv2.rectangle(img, (round(x0), round(y0)), (round(x1), round(y1)), colour, -1)


def draw_facade(
    style: FacadeStyle,
    length_m: float,
    height_m: float,
    px_per_m: float,
    rng: np.random.Generator,
    detail: float = 1.0,
) -> np.ndarray:
    """Draw one building front.

    Parameters
    ----------
    style : FacadeStyle
    length_m, height_m : float
        Size of the front.
    px_per_m : float
        Texture resolution.
    rng : numpy.random.Generator
        Source of the per-building variation.
    detail : float
        Expected number of individual details (posters, signs, trees, ...) per 10 m of front.

    Returns
    -------
    ndarray of uint8, shape (round(height_m * px_per_m), round(length_m * px_per_m), 3), BGR
    """
    s = px_per_m
    h, w = max(2, round(height_m * s)), max(2, round(length_m * s))
    img = _base_front(style, h, w, s, rng)
    if style.cornice:
        _rect(img, 0, 0, w, 0.5 * s, _vary(style.frame, rng, 20))
    for _ in range(rng.poisson(detail * length_m / 10.0)):
        _detail(img, s, rng)

    # Grime: low-frequency stains plus texel noise, so blank wall still has some gradient.
    stains = cv2.resize(rng.normal(0, 1, (max(2, h // 24), max(2, w // 24))), (w, h))
    noise = rng.normal(0, style.noise, (h, w, 1)) + 8.0 * stains[:, :, None]
    out: np.ndarray = np.clip(img + noise, 0, 255).astype(np.uint8)
    return out


def _base_front(
    style: FacadeStyle, h: int, w: int, s: float, rng: np.random.Generator
) -> np.ndarray:
    """Wall colour and pattern, shop front, windows."""
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = _vary(style.wall, rng, 12)
    _wall_pattern(img, style, s)
    shop_h = 0.0
    if style.shop:
        shop_h = 3.6 * s
        _shop_front(img, style, s, shop_h, rng)
    _windows(img, style, s, shop_h, rng)
    return img


def _wall_pattern(img: np.ndarray, style: FacadeStyle, s: float) -> None:
    h, w = img.shape[:2]
    b, g, r = (max(0, c - 30) for c in style.wall)
    dark = (b, g, r)
    if style.pattern == "brick":
        step = max(2, round(0.3 * s))
        for y in range(0, h, step):
            cv2.line(img, (0, y), (w, y), dark, 1)
    elif style.pattern == "panels":
        step = max(4, round(2.5 * s))
        for x in range(0, w, step):
            cv2.line(img, (x, 0), (x, h), dark, 1)
        for y in range(0, h, max(4, round(style.floor_m * s))):
            cv2.line(img, (0, y), (w, y), dark, 1)
    elif style.pattern == "stripes":
        band = max(2, round(style.floor_m * s))
        for y in range(0, h, 2 * band):
            _rect(img, 0, y + band * 0.7, w, y + band, dark)


def _shop_front(
    img: np.ndarray, style: FacadeStyle, s: float, shop_h: float, rng: np.random.Generator
) -> None:
    h, w = img.shape[:2]
    top = h - shop_h
    _rect(img, 0, top, w, h, _vary(style.wall, rng, 30))
    x = float(rng.uniform(0.3, 1.5) * s)
    while x < w - 1.5 * s:
        unit = float(rng.uniform(3.0, 7.0) * s)
        right = min(w - 0.3 * s, x + unit)
        glass = _vary(style.glass, rng, 25)
        _rect(img, x, top + 1.2 * s, right, h - 0.3 * s, glass)
        if rng.random() < 0.5:  # a door in the shop window
            dx = x + (right - x) * float(rng.uniform(0.1, 0.6))
            _rect(img, dx, top + 1.3 * s, dx + 1.0 * s, h, _vary(style.frame, rng, 30))
        # Awning (sometimes striped) and a sign board with "text".
        awning = _vary(style.awning, rng, 40)
        _rect(img, x - 0.2 * s, top + 0.5 * s, right + 0.2 * s, top + 1.2 * s, awning)
        if rng.random() < 0.5:
            stripe = max(2, round(0.4 * s))
            for sx in range(round(x), round(right), 2 * stripe):
                _rect(img, sx, top + 0.5 * s, sx + stripe, top + 1.2 * s, (235, 235, 235))
        board = _vary((40, 40, 40) if rng.random() < 0.5 else (225, 225, 225), rng, 20)
        _rect(img, x, top, right, top + 0.5 * s, board)
        _text(img, x + 0.2 * s, top + 0.45 * s, right - x - 0.4 * s, 0.4 * s, rng)
        x = right + float(rng.uniform(0.3, 1.5) * s)


def _windows(
    img: np.ndarray, style: FacadeStyle, s: float, shop_h: float, rng: np.random.Generator
) -> None:
    h, w = img.shape[:2]
    floor = style.floor_m * s
    ww, wh, pitch = style.window_w_m * s, style.window_h_m * s, style.window_pitch_m * s
    columns = max(1, int((w - 0.5 * s) // pitch))
    margin = (w - columns * pitch) / 2
    bottom = h - (shop_h if shop_h else floor * 0.1)
    y = bottom - floor
    while y > 0.8 * s:
        sill = y + (floor - wh) * 0.55
        for c in range(columns):
            cx = margin + (c + 0.5) * pitch
            x0, x1 = cx - ww / 2, cx + ww / 2
            _rect(
                img,
                x0 - 0.12 * s,
                sill - 0.12 * s,
                x1 + 0.12 * s,
                sill + wh + 0.12 * s,
                style.frame,
            )
            glass = _vary(style.glass, rng, 18)
            _rect(img, x0, sill, x1, sill + wh, glass)
            state = rng.random()
            if state < 0.25:  # curtains: a lighter upper part
                _rect(
                    img,
                    x0,
                    sill,
                    x1,
                    sill + wh * float(rng.uniform(0.3, 0.8)),
                    _vary((200, 200, 190), rng, 40),
                )
            elif state < 0.35:  # open window: dark
                _rect(img, x0, sill, x1, sill + wh, (15, 15, 15))
            if ww > 1.2 * s:  # mullion
                cv2.line(
                    img, (round(cx), round(sill)), (round(cx), round(sill + wh)), style.frame, 1
                )
            if style.balconies and rng.random() < 0.5:
                _rect(
                    img,
                    x0 - 0.3 * s,
                    sill + wh,
                    x1 + 0.3 * s,
                    sill + wh + 0.9 * s,
                    _vary(style.frame, rng, 25),
                )
        y -= floor


def _text(
    img: np.ndarray,
    x: float,
    baseline: float,
    width: float,
    height: float,
    rng: np.random.Generator,
) -> None:
    if width < 4 or height < 3:
        return
    scale = height / 22.0
    letters = max(1, int(width / (14 * scale)))
    text = "".join(rng.choice(list(string.ascii_uppercase), size=min(letters, 12)))
    colour = _colour(rng, 0, 256)
    cv2.putText(
        img,
        text,
        (round(x), round(baseline)),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        colour,
        1,
        cv2.LINE_AA,
    )


def _detail(img: np.ndarray, s: float, rng: np.random.Generator) -> None:
    """One individual feature: what makes a building recognisable among look-alikes."""
    h, w = img.shape[:2]
    kind = rng.integers(6)
    x = float(rng.uniform(0, w))
    if kind == 0:  # poster or billboard
        pw, ph = float(rng.uniform(1.0, 4.0) * s), float(rng.uniform(1.0, 3.0) * s)
        y = h - float(rng.uniform(1.0, min(8.0, h / s)) * s)
        _rect(img, x, y - ph, x + pw, y, _colour(rng, 0, 256))
        _rect(img, x + pw * 0.15, y - ph * 0.8, x + pw * 0.7, y - ph * 0.5, _colour(rng, 0, 256))
    elif kind == 1:  # graffiti: a few thick random strokes near the ground
        points = np.stack(
            [x + rng.uniform(-2, 2, 5) * s, h - rng.uniform(0.3, 2.2, 5) * s], axis=1
        ).astype(np.int32)
        cv2.polylines(
            img, [points], False, _colour(rng, 0, 256), max(1, round(0.15 * s)), cv2.LINE_AA
        )
    elif kind == 2:  # pole with a sign
        top = h - float(rng.uniform(3.0, 5.0) * s)
        cv2.line(img, (round(x), h), (round(x), round(top)), (90, 90, 90), max(1, round(0.15 * s)))
        colour = [(40, 40, 200), (200, 90, 20), (30, 180, 230), (240, 240, 240)][rng.integers(4)]
        if rng.random() < 0.5:
            cv2.circle(
                img, (round(x), round(top)), max(2, round(0.45 * s)), colour, -1, cv2.LINE_AA
            )
        else:
            _rect(img, x - 0.5 * s, top - 0.4 * s, x + 0.5 * s, top + 0.4 * s, colour)
    elif kind == 3:  # tree in front of the wall
        trunk_top = h - 2.5 * s
        cv2.line(
            img, (round(x), h), (round(x), round(trunk_top)), (30, 50, 70), max(1, round(0.3 * s))
        )
        green = (int(rng.integers(20, 70)), int(rng.integers(90, 170)), int(rng.integers(20, 80)))
        for _ in range(6):
            cx = x + float(rng.normal(0, 0.9)) * s
            cy = trunk_top - float(rng.uniform(0.5, 2.5)) * s
            cv2.circle(
                img,
                (round(cx), round(cy)),
                max(2, round(rng.uniform(0.8, 1.6) * s)),
                _vary(green, rng, 25),
                -1,
                cv2.LINE_AA,
            )
    elif kind == 4:  # air conditioners / boxes on the wall
        y = float(rng.uniform(0.1, 0.8)) * h
        for _ in range(int(rng.integers(1, 4))):
            _rect(img, x, y, x + 0.8 * s, y + 0.6 * s, (170, 175, 180))
            x += float(rng.uniform(1.0, 3.0)) * s
    else:  # drain pipe
        cv2.line(img, (round(x), 0), (round(x), h), (60, 60, 60), max(1, round(0.12 * s)))


def draw_skyline(
    length_m: float, height_m: float, px_per_m: float, rng: np.random.Generator
) -> np.ndarray:
    """A distant, hazy skyline for the walls that close the city off."""
    h, w = max(2, round(height_m * px_per_m)), max(2, round(length_m * px_per_m))
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = (150, 140, 130)
    x = 0.0
    while x < w:
        bw = float(rng.uniform(6, 25) * px_per_m)
        top = float(rng.uniform(0.0, 0.6) * h)
        shade = int(rng.integers(90, 140))
        _rect(img, x, top, x + bw, h, (shade + 10, shade, shade - 10))
        x += bw
    noise = rng.normal(0, 4, (h, w, 1))
    return np.clip(img + noise, 0, 255).astype(np.uint8)
