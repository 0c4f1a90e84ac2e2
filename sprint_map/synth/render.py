"""A pinhole camera view of the city by 2-D ray casting (the "Wolfenstein" technique).

The city is a set of vertical walls on a flat ground. For every image column one ray is cast in
the ground plane; the nearest wall it hits fixes that column's depth and the texture column.
Rows above the wall's top are sky, rows below the horizon beyond the wall's foot are ground
(sampled from a top-down ground map by floor casting). The result is an exact perspective view
for a level camera: moving forward enlarges and shifts facades the way a real camera does, and
two traversals at the same pose see the same image.

The view is rendered at ``supersample`` times the output size and reduced with ``INTER_AREA``,
which removes the shimmer of unfiltered texture minification. Cost for a 160x120 output
(320x240 internally, ~320 walls of which ~80 face the camera and lie ahead of it): about 2.5 ms,
half of it building the per-pixel remap tables, a fifth the ray/wall intersections.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sprint_map.synth.atlas import Atlas
from sprint_map.synth.layout import CityLayout
from sprint_map.util.arrays import Float32Array, Image

__all__ = ["BGR", "Camera", "Renderer", "View"]

_FAR = 1.0e4  # depth given to sky pixels (metres)

BGR = tuple[int, int, int]


@dataclass(frozen=True)
class Camera:
    """Image size and field of view."""

    width: int = 160
    height: int = 120
    fov_deg: float = 90.0
    supersample: int = 2

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ValueError("image must be at least 8 x 8")
        if not 10 <= self.fov_deg <= 150:
            raise ValueError("fov_deg must be in [10, 150]")
        if self.supersample < 1:
            raise ValueError("supersample must be >= 1")


@dataclass(frozen=True)
class View:
    """A rendered view: the image plus per-pixel depth (for fog) and sky/ground fractions."""

    image: Image  # (H, W, 3) uint8 BGR
    depth: Float32Array  # (H, W) float32 metres along the optical axis; sky: 1e4
    sky: Float32Array  # (H, W) float32 in [0, 1], fraction of the pixel that is sky
    ground: Float32Array  # (H, W) float32 in [0, 1], fraction of the pixel that is ground


class Renderer:
    """Renders views of one city.

    Parameters
    ----------
    layout : CityLayout
    atlas : Atlas
        Textures of ``layout``'s buildings, in the same order.
    camera : Camera
    """

    def __init__(self, layout: CityLayout, atlas: Atlas, camera: Camera) -> None:
        self.layout = layout
        self.atlas = atlas
        self.camera = camera
        b = layout.buildings
        self._p0 = np.array([w.p0 for w in b], dtype=np.float64)
        self._p1 = np.array([w.p1 for w in b], dtype=np.float64)
        self._edge = self._p1 - self._p0
        # Front normal: the wall direction rotated clockwise (see layout.build_layout).
        self._normal = np.stack([self._edge[:, 1], -self._edge[:, 0]], axis=1)
        self._height = np.array([w.height_m for w in b], dtype=np.float64)
        self._rects = atlas.rects.astype(np.float32)
        ss = camera.supersample
        self._w, self._h = camera.width * ss, camera.height * ss
        self._focal = (self._w / 2) / np.tan(np.radians(camera.fov_deg) / 2)
        # Angle of each column's ray relative to the optical axis (positive = to the left).
        columns = np.arange(self._w) + 0.5
        self._col_angle = np.arctan2(self._w / 2 - columns, self._focal)
        self._cos_col = np.cos(self._col_angle)
        self._rows = np.arange(self._h, dtype=np.float32) + np.float32(0.5)
        self._sky_cache: dict[tuple[tuple[BGR, BGR], float], np.ndarray] = {}

    def render(
        self,
        x: float,
        y: float,
        heading_deg: float,
        height_m: float = 1.6,
        pitch_px: float = 0.0,
        sky: tuple[BGR, BGR] = ((235, 200, 150), (250, 235, 215)),
    ) -> View:
        """Render the view from ``(x, y)`` looking along ``heading_deg``.

        Parameters
        ----------
        x, y : float
            Camera position (metres).
        heading_deg : float
            Viewing direction, degrees counter-clockwise from +x.
        height_m : float
            Camera height above the ground.
        pitch_px : float
            Horizon shift in output pixels (positive: horizon lower, camera pitched up).
        sky : pair of BGR colours
            Sky gradient, top and horizon.
        """
        origin = np.array([x, y], dtype=np.float64)
        angles = np.radians(heading_deg) + self._col_angle
        rays = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (W, 2)

        # Only walls whose front faces the camera can be the nearest hit (blocks are solid), and
        # only if some part of them is in front of the camera (90+ degree fields of view aside,
        # this halves the walls to intersect).
        to_cam = origin - self._p0
        forward = rays[self._w // 2]
        ahead = np.maximum(-(to_cam @ forward), (self._p1 - origin) @ forward) > 0
        facing = np.nonzero(((self._normal * to_cam).sum(axis=1) > 0) & ahead)[0]
        if len(facing) == 0:
            raise ValueError(f"camera at ({x:.1f}, {y:.1f}) is outside the city")
        p0, edge = self._p0[facing], self._edge[facing]
        w = p0 - origin  # (n, 2)
        denom = rays[:, None, 0] * edge[None, :, 1] - rays[:, None, 1] * edge[None, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = (w[None, :, 0] * edge[None, :, 1] - w[None, :, 1] * edge[None, :, 0]) / denom
            along = (w[None, :, 0] * rays[:, None, 1] - w[None, :, 1] * rays[:, None, 0]) / denom
        valid = (dist > 1e-3) & (along >= 0) & (along <= 1)
        dist = np.where(valid, dist, np.inf)
        nearest = dist.argmin(axis=1)
        cols = np.arange(self._w)
        hit_dist = dist[cols, nearest]
        if not np.isfinite(hit_dist).all():
            raise ValueError(f"camera at ({x:.1f}, {y:.1f}) is outside the city")
        wall = facing[nearest]
        u = along[cols, nearest]
        depth_col = hit_dist * self._cos_col  # along the optical axis: no fisheye

        # Everything per pixel is an outer product of a per-row and a per-column term, built in
        # float32: this part dominates the frame time, the ray casting above is ~0.8 ms.
        f = self._focal
        horizon = self._h / 2 + pitch_px * self.camera.supersample
        rows = self._rows - np.float32(horizon)  # (H,), positive below the horizon
        top = self._height[wall]
        rects = self._rects[wall]
        top_row = (-(top - height_m) * f / depth_col).astype(np.float32)  # wall top, rel. horizon
        foot_row = (height_m * f / depth_col).astype(np.float32)  # wall foot
        is_sky = rows[:, None] < top_row[None, :]
        is_ground = rows[:, None] >= foot_row[None, :]

        # Walls: texture column fixed per image column, texture row linear in the image row.
        tex_x = (rects[:, 0] + np.clip(u * rects[:, 2] - 0.5, 0, rects[:, 2] - 1)).astype(
            np.float32
        )
        scale = rects[:, 3] / top  # texels per metre, vertically
        slope = (depth_col / f * scale).astype(np.float32)
        offset = ((top - height_m) * scale - 0.5).astype(np.float32)
        tex_y = np.clip(
            rows[:, None] * slope[None, :] + offset[None, :], 0, (rects[:, 3] - 1)[None, :]
        )
        tex_y += rects[None, :, 1].astype(np.float32)

        # Ground: the floor point seen at row r lies height*f/r ahead along the optical axis.
        g = self.atlas.ground_px_per_m
        xmin, _, _, ymax = self.layout.extent
        gh, gw = self.atlas.ground_shape
        with np.errstate(divide="ignore"):
            ground_depth = np.where(rows > 0, np.float32(height_m * f) / rows, np.float32(_FAR))
        reach = ground_depth[:, None] / self._cos_col[None, :].astype(np.float32)
        gx = np.clip(
            np.float32((x - xmin) * g - 0.5) + reach * (rays[:, 0] * g).astype(np.float32),
            0,
            gw - 1,
        )
        gy = np.clip(
            np.float32((ymax - y) * g - 0.5) - reach * (rays[:, 1] * g).astype(np.float32),
            0,
            gh - 1,
        )

        map_x = np.where(is_ground, gx, tex_x[None, :])
        map_y = np.where(is_ground, gy, tex_y)
        image = cv2.remap(
            self.atlas.image,
            map_x.astype(np.float32, copy=False),
            map_y.astype(np.float32, copy=False),
            cv2.INTER_LINEAR,
        )
        sky_u8 = is_sky.view(np.uint8)
        cv2.copyTo(self._sky_image(sky, horizon), sky_u8, image)
        depth = np.where(
            is_ground,
            ground_depth[:, None],
            np.where(is_sky, np.float32(_FAR), depth_col.astype(np.float32)),
        )

        ss = self.camera.supersample
        out = (self.camera.width, self.camera.height)
        sky_frac = is_sky.astype(np.float32)
        ground_frac = is_ground.astype(np.float32)
        if ss > 1:
            image = cv2.resize(image, out, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, out, interpolation=cv2.INTER_AREA)
            sky_frac = cv2.resize(sky_frac, out, interpolation=cv2.INTER_AREA)
            ground_frac = cv2.resize(ground_frac, out, interpolation=cv2.INTER_AREA)
        return View(image, depth, sky_frac, ground_frac)

    def _sky_image(self, sky: tuple[BGR, BGR], horizon: float) -> np.ndarray:
        """Full-size sky gradient (cached: sky colours and horizon repeat from frame to frame)."""
        # Whole supersampled pixels: camera shake moves the horizon every frame, and a gradient
        # off by half a pixel is invisible, so this keeps the cache hit rate high.
        horizon = float(round(horizon))
        key = (sky, horizon)
        cached = self._sky_cache.get(key)
        if cached is None:
            weight = np.clip(self._rows / max(horizon, 1.0), 0, 1)[:, None]
            column = (1 - weight) * np.array(sky[0]) + weight * np.array(sky[1])  # (H, 3)
            cached = np.ascontiguousarray(
                np.broadcast_to(column[:, None, :], (self._h, self._w, 3)).astype(np.uint8)
            )
            if len(self._sky_cache) > 64:
                self._sky_cache.clear()
            self._sky_cache[key] = cached
        return cached
