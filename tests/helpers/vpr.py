"""A small VPR-layout data set: database/ and queries/ of @UTM-named images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from sprint_map.util.geo import lonlat_of_utm

ZONE, LETTER = 32, "V"  # Norway: northern hemisphere


def vpr_name(east: float, north: float, timestamp: str = "", zone: int = ZONE,
             letter: str = LETTER, prefix: str = "") -> str:
    lat, lon = lonlat_of_utm(east, north, zone, False)
    fields = [prefix, f"{east:.2f}", f"{north:.2f}", str(zone), letter, f"{float(lat):.5f}",
              f"{float(lon):.5f}", "pano", "0", "0", "0", "0", "0", timestamp, "", ".jpg"]
    return "@".join(fields)


def place_images(n: int, seed: int, size: int = 64) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [cv2.resize(rng.integers(0, 256, (size // 8, size // 8, 3), dtype=np.uint8),
                       (size, size), interpolation=cv2.INTER_CUBIC) for _ in range(n)]


def make_vpr_dataset(root: Path, n_places: int = 30, spacing_m: float = 10.0, seed: int = 0,
                     db_timestamps: bool = True, query_every: int = 2,
                     noise: float = 12.0, prefix: bool = False) -> Path:
    """Places every ``spacing_m`` metres north; the database sees each once (names with
    timestamps, which order them differently from their names), the queries every
    ``query_every``-th place again, with noise and a brightness change (no timestamps).
    ``prefix``: names start ``img<k>@`` (the layout allows a prefix), ``k`` counting down the
    database's route, so the prefix orders it the other way from its timestamps too."""
    rng = np.random.default_rng(seed + 1)
    places = place_images(n_places, seed)
    (root / "database").mkdir(parents=True)
    (root / "queries").mkdir()
    east0, north0 = 597000.0, 6643000.0
    for i, image in enumerate(places):
        noisy = np.clip(image + rng.normal(0, 8, image.shape), 0, 255).astype(np.uint8)
        stamp = f"{1000 + i}" if db_timestamps else ""
        # eastings that decrease along the route: name order is the reverse of time order
        name = vpr_name(east0 - i * 0.05, north0 + i * spacing_m, stamp,
                        prefix=f"img{n_places - i:03d}" if prefix else "")
        cv2.imwrite(str(root / "database" / name), noisy)
    for i in range(0, n_places, query_every):
        shaken = np.clip(places[i] * 0.8 + 20 + rng.normal(0, noise, places[i].shape), 0, 255)
        # one easting: name order (by northing) is time order
        name = vpr_name(east0 + 1.0, north0 + i * spacing_m + 2.0,
                        prefix=f"img{i:03d}" if prefix else "")
        cv2.imwrite(str(root / "queries" / name), shaken.astype(np.uint8))
    return root
