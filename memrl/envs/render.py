"""Bird's-eye-view rendering of the lane-change scene with OpenCV.

The road runs up the picture (driving direction up, lane 0 on the left). Lateral and
longitudinal scales are separate, so an 84x84 crop spends its pixels on the road: with the
defaults (0.2 m/px across, 0.8 m/px along) it shows 16.8 m across and 33.6 m ahead and behind.

Pixel convention: pixel (row i, col j) covers the continuous square [j, j+1) x [i, i+1); the
point the crop is centred on maps to the continuous point (W/2, H/2).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

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
        palette: dict[str, tuple[int, int, int]] | None = None,
    ) -> None:
        self.view = view
        self.lanes_count = lanes_count
        self.lane_width = lane_width
        self.show_target_lane = show_target_lane
        self.dash_length = dash_length
        self.palette = dict(PALETTE if palette is None else palette)
        self._half_span = 0.5 * view.height * view.longitudinal_scale  # [m] ahead/behind shown

    def to_pixels(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map world points ``[..., (x, y)]`` [m] to continuous pixel coordinates ``(col, row)``."""
        v = self.view
        col = 0.5 * v.width + (points[..., 1] - center[1]) / v.lateral_scale
        row = 0.5 * v.height - (points[..., 0] - center[0]) / v.longitudinal_scale
        return np.stack([col, row], axis=-1)

    def _fill(self, img: np.ndarray, polys: list[np.ndarray], color: tuple[int, int, int]) -> None:
        # Continuous coords -> OpenCV's pixel-centre coords, fixed point.
        pts = [np.round((p - 0.5) * _ONE).astype(np.int32) for p in polys]
        if len(pts) == 1:
            cv2.fillConvexPoly(img, pts[0], color, lineType=cv2.LINE_8, shift=_SHIFT)
        elif pts:
            cv2.fillPoly(img, pts, color, lineType=cv2.LINE_8, shift=_SHIFT)

    def _band(self, center: np.ndarray, y0: float, y1: float, x0: float, x1: float) -> np.ndarray:
        """Axis-aligned world rectangle [x0, x1] x [y0, y1] as a pixel polygon."""
        corners = np.array([[x0, y0], [x0, y1], [x1, y1], [x1, y0]], dtype=np.float64)
        return self.to_pixels(center, corners)

    def render(
        self,
        center: np.ndarray,
        vehicles: Iterable[CurvatureVehicle],
        target_lane: int | None = None,
        ego: CurvatureVehicle | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Draw the scene around ``center`` (x, y) [m].

        Args:
            center: world point at the crop centre, usually a car's position.
            vehicles: cars to draw, each in the shade of its ``kind``; draw order is the
                iteration order.
            target_lane: lane painted in the target shade (when ``show_target_lane``).
            ego: the car whose view this is, drawn in the 'agent' shade. When it is not the
                agent, the agent is drawn as a 'learned' car: to a car driven by a copy of
                the agent, the agent is another learning driver.
            out: optional ``(H, W, 3)`` uint8 array to draw into.

        Returns:
            ``(H, W, 3)`` uint8 RGB picture.
        """
        v, w, p = self.view, self.lane_width, self.palette
        img = out if out is not None else np.empty((v.height, v.width, 3), dtype=np.uint8)
        img[:] = p["offroad"]
        x_lo, x_hi = center[0] - self._half_span - 1.0, center[0] + self._half_span + 1.0
        left, right = -0.5 * w, (self.lanes_count - 0.5) * w
        self._fill(img, [self._band(center, left, right, x_lo, x_hi)], p["road"])
        if self.show_target_lane and target_lane is not None:
            y = target_lane * w
            self._fill(img, [self._band(center, y - 0.5 * w, y + 0.5 * w, x_lo, x_hi)],
                       p["target_lane"])
        half_line = 0.5 * min(v.lateral_scale, 0.15)  # markings: 1 px or 0.15 m wide
        edges = [self._band(center, y - half_line, y + half_line, x_lo, x_hi)
                 for y in (left + half_line, right - half_line)]
        period = 2.0 * self.dash_length
        first = np.floor(x_lo / period) * period
        starts = np.arange(first, x_hi, period)
        dashes = [
            self._band(center, y - half_line, y + half_line, s, s + self.dash_length)
            for y in (np.arange(1, self.lanes_count) - 0.5) * w
            for s in starts
        ]
        self._fill(img, edges + dashes, p["marking"])
        reach = self._half_span + 10.0
        for car in vehicles:
            if abs(car.position[0] - center[0]) > reach:
                continue
            kind = "agent" if car is ego else ("learned" if car.kind == "agent" else car.kind)
            self._fill(img, [self.to_pixels(center, car.polygon()[:4])], p[kind])
        return img
