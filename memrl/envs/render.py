"""Bird's-eye-view rendering of the lane-change scene with OpenCV.

The road runs up the picture (driving direction up, lane 0 on the left). Lateral and
longitudinal scales are separate, so an 84x84 crop spends its pixels on the road: with the
defaults (0.2 m/px across, 0.8 m/px along) it shows 16.8 m across and 33.6 m ahead and behind.

Pixel convention: pixel (row i, col j) covers the continuous square [j, j+1) x [i, i+1); the
point the crop is centred on maps to the continuous point (W/2, H/2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torchrl.envs.transforms.functional import rgb_to_grayscale

from memrl.envs.vehicles import CurvatureVehicle

PALETTE: dict[str, tuple[int, int, int]] = {
    "offroad": (0, 0, 0),
    "road": (64, 64, 64),
    "target_lane": (80, 104, 80),
    "marking": (255, 255, 255),
    "constant": (30, 200, 30),
    "learned": (90, 190, 255),
    "agent": (255, 220, 0),
}
"""RGB shades. Chosen so that their grayscale levels (ITU-R 601 weights, as TorchRL's
``GrayScale``) stay at least 25 levels apart: 0, 64, 94, 130, 167, 205, 255."""

Color = tuple[int, int, int] | int


def gray_palette(palette: dict[str, tuple[int, int, int]]) -> dict[str, int]:
    """Grayscale level of each shade, computed by TorchRL's own RGB -> gray conversion."""
    rgb = torch.tensor(list(palette.values()), dtype=torch.uint8).T[:, :, None]  # [3, K, 1]
    gray = rgb_to_grayscale(rgb)[0, :, 0].tolist()
    return dict(zip(palette, (int(g) for g in gray), strict=True))


_SHIFT = 4  # OpenCV fixed-point fractional bits: sub-pixel accurate polygon corners
_ONE = 1 << _SHIFT


@dataclass
class View:
    """A crop geometry: size [px] and scales [m/px]."""

    width: int
    height: int
    lateral_scale: float
    longitudinal_scale: float


class BEVRenderer:
    """Draws the road and cars of a scene into an RGB uint8 picture centred on any point."""

    def __init__(
        self,
        view: View,
        lanes_count: int,
        lane_width: float,
        *,
        show_target_lane: bool = True,
        dash_length: float = 3.0,
        path_length: float = 0.0,
        palette: dict[str, tuple[int, int, int]] | None = None,
        channels: int = 3,
    ) -> None:
        """Args:
            view: crop size and scales.
            lanes_count: lanes of the road (lane i centred at y = i * lane_width).
            lane_width: [m].
            show_target_lane: paint the target lane in its own shade.
            dash_length: lane-marking dash (and gap) length [m].
            path_length: length [m] of the ``ego`` car's path drawn ahead of it at its
                current heading and curvature (0: none).
            palette: RGB shades by name (default :data:`PALETTE`).
            channels: 3 for RGB; 1 draws each shade's grayscale level directly, equal to
                TorchRL's ``GrayScale`` of the RGB picture at a third of the drawing work.
        """
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels}")
        self.channels = channels
        self.view = view
        self.lanes_count = lanes_count
        self.lane_width = lane_width
        self.show_target_lane = show_target_lane
        self.dash_length = dash_length
        self.path_length = path_length
        rgb = dict(PALETTE if palette is None else palette)
        self.palette: dict[str, Color] = dict(rgb) if channels == 3 else dict(gray_palette(rgb))
        self._half_span = 0.5 * view.height * view.longitudinal_scale  # [m] ahead/behind shown

    def to_pixels(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map world points ``[..., (x, y)]`` [m] to continuous pixel coordinates ``(col, row)``."""
        v = self.view
        col = 0.5 * v.width + (points[..., 1] - center[1]) / v.lateral_scale
        row = 0.5 * v.height - (points[..., 0] - center[0]) / v.longitudinal_scale
        return np.stack([col, row], axis=-1)

    def _fill_poly(self, img: np.ndarray, poly: np.ndarray, color: Color) -> None:
        """Fill a convex polygon ``[4, (col, row)]`` given in continuous pixel coordinates."""
        # Continuous coords -> OpenCV's pixel-centre coords (-0.5). OpenCV fills every pixel
        # whose centre is on or inside the outline, so pull each corner in by half a pixel per
        # axis: a box spanning [a, b) then covers exactly the pixels with centres in it.
        inward = 0.5 * np.sign(poly - poly.mean(axis=0))
        pts = np.round((poly - 0.5 - inward) * _ONE).astype(np.int32)
        cv2.fillConvexPoly(img, pts, color, lineType=cv2.LINE_8, shift=_SHIFT)

    def _cols(self, center: np.ndarray, y0: float, y1: float) -> slice:
        """Pixel columns whose centres lie in the world band [y0, y1) across the road."""
        v = self.view
        a = 0.5 * v.width + (y0 - center[1]) / v.lateral_scale
        b = 0.5 * v.width + (y1 - center[1]) / v.lateral_scale
        return slice(max(int(np.ceil(a - 0.5)), 0), max(int(np.ceil(b - 0.5)), 0))

    def _background(self, img: np.ndarray, center: np.ndarray, target_lane: int | None) -> None:
        """Road, target lane and markings: axis-aligned, so filled by slicing (exact, fast)."""
        v, p, w, n = self.view, self.palette, self.lane_width, self.lanes_count
        img[:] = p["offroad"]
        left, right = -0.5 * w, (n - 0.5) * w
        img[:, self._cols(center, left, right)] = p["road"]
        if self.show_target_lane and target_lane is not None:
            y = target_lane * w
            img[:, self._cols(center, y - 0.5 * w, y + 0.5 * w)] = p["target_lane"]
        line = max(v.lateral_scale, 0.15)  # markings: at least 1 px, at most 0.15 m wide
        img[:, self._cols(center, left, left + line)] = p["marking"]
        img[:, self._cols(center, right - line, right)] = p["marking"]
        period = 2.0 * self.dash_length
        x_top = center[0] + 0.5 * v.height * v.longitudinal_scale
        starts = np.arange(np.floor((x_top - 2 * self._half_span) / period) * period - period,
                           x_top + period, period)
        # dash [s, s + L] along the road -> rows (row grows backwards along x)
        r0 = np.ceil(0.5 * v.height - (starts + self.dash_length - center[0])
                     / v.longitudinal_scale - 0.5).astype(int).clip(0, v.height)
        r1 = np.ceil(0.5 * v.height - (starts - center[0])
                     / v.longitudinal_scale - 0.5).astype(int).clip(0, v.height)
        for y in (np.arange(1, n) - 0.5) * w:
            cols = self._cols(center, y - 0.5 * line, y + 0.5 * line)
            for i, j in zip(r0, r1, strict=True):
                if j > i:
                    img[i:j, cols] = p["marking"]

    @staticmethod
    def car_corners(vehicles: Sequence[CurvatureVehicle]) -> np.ndarray:
        """Body corners ``[N, 4, (x, y)]`` [m] of cars, from position, heading and size."""
        pos = np.array([c.position for c in vehicles], dtype=np.float64).reshape(-1, 2)
        heading = np.array([c.heading for c in vehicles], dtype=np.float64)
        half = 0.5 * np.array([[c.LENGTH, c.WIDTH] for c in vehicles]).reshape(-1, 2)
        signs = np.array([[-1, -1], [-1, 1], [1, 1], [1, -1]], dtype=np.float64)
        local = signs[None] * half[:, None, :]
        cos, sin = np.cos(heading)[:, None], np.sin(heading)[:, None]
        x = local[..., 0] * cos - local[..., 1] * sin
        y = local[..., 0] * sin + local[..., 1] * cos
        return np.stack([x, y], axis=-1) + pos[:, None, :]

    def render(
        self,
        center: np.ndarray,
        vehicles: Sequence[CurvatureVehicle],
        target_lane: int | None = None,
        ego: CurvatureVehicle | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Draw the scene around ``center`` (x, y) [m].

        Args:
            center: world point at the crop centre, usually a car's position.
            vehicles: cars to draw, each in the shade of its ``kind``; draw order is the
                sequence order.
            target_lane: lane painted in the target shade (when ``show_target_lane``).
            ego: the car whose view this is, drawn in the 'agent' shade. When it is not the
                agent, the agent is drawn as a 'learned' car: to a car driven by a copy of
                the agent, the agent is another learning driver.
            out: optional uint8 array of the result's shape to draw into.

        Returns:
            ``(H, W, 3)`` uint8 RGB picture, or ``(H, W)`` grayscale when ``channels == 1``.
        """
        v, p = self.view, self.palette
        shape = (v.height, v.width, 3) if self.channels == 3 else (v.height, v.width)
        img = out if out is not None else np.empty(shape, dtype=np.uint8)
        self._background(img, center, target_lane)
        cars = [c for c in vehicles if abs(c.position[0] - center[0]) <= self._half_span + 10.0]
        if cars:
            polys = self.to_pixels(center, self.car_corners(cars))
            for car, poly in zip(cars, polys, strict=True):
                kind = "agent" if car is ego else ("learned" if car.kind == "agent" else car.kind)
                self._fill_poly(img, poly, p[kind])
        if ego is not None and self.path_length > 0:
            self._draw_path(img, center, ego)
        return img

    def path_points(self, car: CurvatureVehicle, points: int = 12) -> np.ndarray:
        """``[points, (x, y)]`` [m]: the arc ``car`` drives over ``path_length`` metres at its
        current heading and curvature."""
        s = np.linspace(0.0, self.path_length, points)
        k, h = float(car.curvature), float(car.heading)
        if abs(k) < 1e-9:
            dx, dy = s * np.cos(h), s * np.sin(h)
        else:
            dx = (np.sin(h + k * s) - np.sin(h)) / k
            dy = (np.cos(h) - np.cos(h + k * s)) / k
        return np.stack([car.position[0] + dx, car.position[1] + dy], axis=-1)

    def _draw_path(self, img: np.ndarray, center: np.ndarray, car: CurvatureVehicle) -> None:
        # Hand-written: highway-env draws no planned path in its observations.
        px = self.to_pixels(center, self.path_points(car)) - 0.5  # pixel-centre coords
        cv2.polylines(img, [np.round(px * _ONE).astype(np.int32)], False, self.palette["agent"],
                      1, cv2.LINE_8, shift=_SHIFT)
