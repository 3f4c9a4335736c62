"""Bird's-eye-view rendering of the lane-change scene: many views at once, in torch, on any device.

One rasterizer serves the highway-env reference env (one view per call) and the batched engine
(every observing car of every env in one call), so both give identical pixels by construction.

The road runs up the picture (driving direction up, lane 0 on the left). Lateral and
longitudinal scales are separate, so an 84x84 crop spends its pixels on the road: with the
defaults (0.2 m/px across, 0.8 m/px along) it shows 16.8 m across and 33.6 m ahead and behind.

Pixel convention: pixel (row i, col j) covers the continuous square [j, j+1) x [i, i+1); the
point the crop is centred on maps to the continuous point (W/2, H/2). A pixel takes the shade
of whatever covers its centre: a car (rectangle, closed) covers the pixels whose centres lie
inside it, later cars over earlier ones; the path cue covers every pixel one of its points
(spaced under half a pixel along the arc) falls in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

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
LABELS = tuple(PALETTE)
"""Shade names in label order: a rendered label image holds indices into this tuple."""
LABEL = {name: i for i, name in enumerate(LABELS)}


def gray_palette(palette: dict[str, tuple[int, int, int]]) -> dict[str, int]:
    """Grayscale level of each shade: TorchRL's ``rgb_to_grayscale`` formula, in the same dtypes."""
    # Written out (not imported from torchrl): importing torchrl changes the process's
    # multiprocessing start method, and the env must not have global side effects.
    r, g, b = torch.tensor(list(palette.values()), dtype=torch.uint8).unbind(-1)
    gray = (0.2989 * r + 0.587 * g + 0.114 * b).to(torch.uint8).tolist()
    return dict(zip(palette, (int(v) for v in gray), strict=True))


@dataclass
class View:
    """A crop geometry: size [px] and scales [m/px]."""

    width: int
    height: int
    lateral_scale: float
    longitudinal_scale: float


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


def arc_points(state: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Points ``[..., S, (x, y)]`` [m] at arc lengths ``s`` [S] along the arcs that cars with
    ``state [..., (x, y, heading, curvature)]`` drive at constant curvature."""
    x, y, h, k = (state[..., i, None] for i in range(4))
    straight = k.abs() < 1e-9
    k_safe = torch.where(straight, torch.ones_like(k), k)
    dx = torch.where(straight, s * torch.cos(h), (torch.sin(h + k * s) - torch.sin(h)) / k_safe)
    dy = torch.where(straight, s * torch.sin(h), (torch.cos(h) - torch.cos(h + k * s)) / k_safe)
    return torch.stack([x + dx, y + dy], dim=-1)


class BEVRenderer:
    """Draws ``V`` views of the road and cars at once into uint8 pictures.

    Args:
        view: crop size and scales.
        lanes_count: lanes of the road (lane i centred at y = i * lane_width).
        lane_width: [m].
        car_size: (length, width) of every car [m].
        show_target_lane: paint the target lane in its own shade.
        dash_length: lane-marking dash (and gap) length [m].
        path_length: length [m] of the viewing car's path drawn ahead of it at its current
            heading and curvature (0: none).
        palette: RGB shades by name (default :data:`PALETTE`).
        channels: 3 for RGB; 1 draws each shade's grayscale level directly, equal to
            TorchRL's ``GrayScale`` of the RGB picture.
        device: where the pictures are drawn.
    """

    def __init__(
        self,
        view: View,
        lanes_count: int,
        lane_width: float,
        car_size: tuple[float, float] = (5.0, 2.0),
        *,
        show_target_lane: bool = True,
        dash_length: float = 3.0,
        path_length: float = 0.0,
        palette: dict[str, tuple[int, int, int]] | None = None,
        channels: int = 3,
        device: torch.device | str = "cpu",
    ) -> None:
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels}")
        self.view, self.channels, self.device = view, channels, torch.device(device)
        self.lanes_count, self.lane_width = lanes_count, lane_width
        self.car_length, self.car_width = float(car_size[0]), float(car_size[1])
        self.show_target_lane, self.dash_length, self.path_length = show_target_lane, dash_length, path_length
        rgb = dict(PALETTE if palette is None else palette)
        shades = [rgb[name] for name in LABELS]
        if channels == 3:
            self.table = torch.tensor(shades, dtype=torch.uint8, device=self.device)  # [K, 3]
        else:
            gray = gray_palette(dict(zip(LABELS, shades, strict=True)))
            self.table = torch.tensor([gray[n] for n in LABELS], dtype=torch.uint8, device=self.device)
        self.palette = {n: (tuple(shades[i]) if channels == 3 else int(self.table[i]))
                        for i, n in enumerate(LABELS)}
        f64 = dict(dtype=torch.float64, device=self.device)
        h, w = view.height, view.width
        half_diag = 0.5 * math.hypot(self.car_length, self.car_width)
        # largest window a car's bounding box needs, at any heading [px]
        self._win_rows = math.ceil(2 * half_diag / view.longitudinal_scale) + 3
        self._win_cols = math.ceil(2 * half_diag / view.lateral_scale) + 3
        f32 = dict(dtype=torch.float32, device=self.device)
        self._win_i = torch.arange(self._win_rows, **f32)[:, None]
        self._cols_j = torch.arange(w, device=self.device)
        self._rows_h = torch.arange(h, device=self.device)[None, :]
        self._dividers = torch.tensor((np.arange(1, lanes_count) - 0.5) * lane_width, **f64)
        line = max(view.lateral_scale, 0.15)
        self._div_k = torch.arange(math.ceil(line / view.lateral_scale) + 1, **f64)  # columns per divider
        self._label_ids = torch.arange(len(LABELS), dtype=torch.uint8, device=self.device)
        self._half_span = 0.5 * h * view.longitudinal_scale  # [m] shown ahead and behind
        # dashes that can show in a crop: 2 * half_span of road plus a period on each side
        self._dash_k = torch.arange(math.ceil(2 * self._half_span / (2 * dash_length)) + 3, **f64)
        step = 0.5 * min(view.lateral_scale, view.longitudinal_scale)
        self._path_s = torch.linspace(0.0, path_length, max(2, math.ceil(path_length / step) + 1), **f64)

    # ------------------------------------------------------------------------ batched
    def render_batch(
        self,
        center: torch.Tensor,
        target_lane: torch.Tensor,
        cars: torch.Tensor,
        car_label: torch.Tensor,
        path: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Pictures ``[V, H, W]`` (grayscale) or ``[V, H, W, 3]`` (RGB) of ``V`` views.

        Args:
            center: ``[V, 2]`` world point (x, y) [m] at each crop's centre (float64).
            target_lane: ``[V]`` lane painted in the target shade (-1: none).
            cars: ``[V, C, 3]`` (x, y, heading) of the cars to draw, in draw order.
            car_label: ``[V, C]`` index into :data:`LABELS` of each car (-1: no car in that slot).
            path: ``[V, 4]`` (x, y, heading, curvature) of each view's own car, whose path
                is drawn when ``path_length > 0`` (None: no path).
        """
        v = self.view
        flat = torch.empty(len(center) * v.height * v.width + 1, dtype=torch.uint8, device=self.device)
        self.render_into(flat, 0, center, target_lane, cars, car_label, path)
        img = flat[:-1].view(len(center), v.height, v.width)
        return img if self.channels == 1 else self.table[img.long()]

    def render_into(self, flat: torch.Tensor, start: int, center: torch.Tensor, target_lane: torch.Tensor,
                    cars: torch.Tensor, car_label: torch.Tensor, path: torch.Tensor | None = None) -> None:
        """Draw the ``V`` pictures (labels when RGB) into ``flat[start : start + V * H * W]`` of a
        1-D uint8 buffer whose last element is spare (it takes the writes that fall outside a
        picture); arguments as :meth:`render_batch`."""
        v = self.view
        n_views, size = len(center), v.height * v.width
        # Gray: paint the shades themselves; RGB: paint labels, then look their colours up.
        values = self.table if self.channels == 1 else self._label_ids
        base = start + torch.arange(n_views, device=self.device) * size  # [V] offset of each picture
        self._background(center, target_lane, values, flat, base, start)
        self._paint_cars(flat, base, center, cars, car_label, values)
        if path is not None and self.path_length > 0:
            pts = arc_points(path, self._path_s)  # [V, S, 2]
            rel = pts - center[:, None, :]
            col = torch.floor(0.5 * v.width + rel[..., 1] / v.lateral_scale).long()
            row = torch.floor(0.5 * v.height - rel[..., 0] / v.longitudinal_scale).long()
            ok = (row >= 0) & (row < v.height) & (col >= 0) & (col < v.width)
            index = torch.where(ok, base[:, None] + row * v.width + col, flat.numel() - 1)
            flat.scatter_(0, index.reshape(-1), values[LABEL["agent"]].expand(index.numel()))

    def _background(self, center: torch.Tensor, target_lane: torch.Tensor, values: torch.Tensor,
                    flat: torch.Tensor, base: torch.Tensor, start: int) -> None:
        """Road, target lane and markings into the pictures: a shade per column, copied down
        every row, then the dashes of the lane dividers."""
        v, w, n = self.view, self.lane_width, self.lanes_count
        j, cy = self._cols_j, center[:, 1:2]

        def edges(y: torch.Tensor | float) -> torch.Tensor:
            """The first column whose centre lies at or beyond world y across the road."""
            return torch.ceil(0.5 * v.width + (y - cy) / v.lateral_scale - 0.5)

        def band(y0: torch.Tensor | float, y1: torch.Tensor | float) -> torch.Tensor:
            """[V, W]: columns whose centres lie in the world band [y0, y1) across the road."""
            return (j >= edges(y0)) & (j < edges(y1))

        left, right = -0.5 * w, (n - 0.5) * w
        col = torch.where(band(left, right), values[LABEL["road"]], values[LABEL["offroad"]])
        if self.show_target_lane:
            t = (target_lane.to(torch.float64) * w)[:, None]
            col = torch.where(band(t - 0.5 * w, t + 0.5 * w) & (target_lane[:, None] >= 0),
                              values[LABEL["target_lane"]], col)
        line = max(v.lateral_scale, 0.15)  # markings: at least 1 px, at most 0.15 m wide
        col = torch.where(band(left, left + line) | band(right - line, right), values[LABEL["marking"]], col)
        n_views = len(center)
        pictures = flat[start: start + n_views * v.height * v.width].view(n_views, v.height, v.width)
        pictures.copy_(col[:, None, :].expand(-1, v.height, -1))
        if n < 2:
            return
        # dash k covers [s_k, s_k + L] along the road, s_k = first + k * period: rows [r0, r1)
        period = 2.0 * self.dash_length
        x_top = center[:, 0:1] + 0.5 * v.height * v.longitudinal_scale
        first = torch.floor((x_top - 2 * self._half_span) / period) * period - period
        starts = first + self._dash_k * period  # [V, K]
        cx, lon = center[:, 0:1], v.longitudinal_scale
        r0 = torch.ceil(0.5 * v.height - (starts + self.dash_length - cx) / lon - 0.5)
        r1 = torch.ceil(0.5 * v.height - (starts - cx) / lon - 0.5)
        # +1 where a dash starts, -1 where it ends, summed down the picture
        count = torch.zeros(n_views, v.height + 1, dtype=r0.dtype, device=self.device)
        count.scatter_add_(1, r0.clamp(0, v.height).long(), torch.ones_like(r0))
        count.scatter_add_(1, r1.clamp(0, v.height).long(), -torch.ones_like(r0))
        dash = count[:, :-1].cumsum(1) > 0  # [V, H]
        # the divider columns: those of the bands [yd - line/2, yd + line/2), at most a few each
        yd = self._dividers - 0.5 * line  # [D]
        a, b = edges(yd), edges(yd + line)  # [V, D]
        cols = (a[..., None] + self._div_k).long()  # [V, D, k]
        ok = (cols < b[..., None]) & (cols >= 0) & (cols < v.width)
        cols, ok = cols.reshape(n_views, 1, -1), ok.reshape(n_views, 1, -1)
        pixel = base[:, None, None] + self._rows_h[:, :, None] * v.width + cols  # [V, H, D * k]
        index = torch.where(dash[..., None] & ok, pixel, flat.numel() - 1)
        flat.scatter_(0, index.reshape(-1), values[LABEL["marking"]].expand(index.numel()))

    def _paint_cars(self, flat: torch.Tensor, base: torch.Tensor, center: torch.Tensor, cars: torch.Tensor,
                    car_label: torch.Tensor, values: torch.Tensor) -> None:
        """Paint each car over the pixels whose centres its body covers, slot after slot
        (later cars over earlier ones): per picture row, the run of columns inside the body."""
        v = self.view
        if car_label.numel() == 0:
            return
        rel = (cars[..., :2] - center[:, None, :]).to(torch.float32)  # [V, C, 2] car from view centre [m]
        heading = cars[..., 2]
        cos, sin = torch.cos(heading).to(torch.float32), torch.sin(heading).to(torch.float32)
        half_len, half_wid = 0.5 * self.car_length, 0.5 * self.car_width
        # rows whose centres lie within the body's extent along the road
        half_x = half_len * cos.abs() + half_wid * sin.abs()  # [m]
        row_c = 0.5 * v.height - rel[..., 0] / v.longitudinal_scale  # car centre [continuous px]
        first = torch.ceil(row_c - half_x / v.longitudinal_scale - 0.5)
        last = torch.floor(row_c + half_x / v.longitudinal_scale - 0.5)
        n_rows = int((last - first).max()) + 1 if self.device.type == "cpu" else self._win_rows
        row = first[..., None] + self._win_i[:n_rows, 0]  # [V, C, R]
        dx = (0.5 * v.height - 0.5 - row) * v.longitudinal_scale - rel[..., 0, None]  # row centre - car [m]
        c, s = cos[..., None], sin[..., None]
        # |dx c + dy s| <= L/2 and |dy c - dx s| <= W/2, solved for dy on each row
        inf = torch.tensor(float("inf"), device=self.device)
        s_safe, c_safe = torch.where(s == 0, 1.0, s), torch.where(c == 0, 1.0, c)
        a0, a1 = (-half_len - dx * c) / s_safe, (half_len - dx * c) / s_safe
        a_lo, a_hi = torch.minimum(a0, a1), torch.maximum(a0, a1)
        a_ok = (dx * c).abs() <= half_len
        a_lo = torch.where(s == 0, torch.where(a_ok, -inf, inf), a_lo)
        a_hi = torch.where(s == 0, torch.where(a_ok, inf, -inf), a_hi)
        b0, b1 = (-half_wid + dx * s) / c_safe, (half_wid + dx * s) / c_safe
        b_lo, b_hi = torch.minimum(b0, b1), torch.maximum(b0, b1)
        b_ok = (dx * s).abs() <= half_wid
        b_lo = torch.where(c == 0, torch.where(b_ok, -inf, inf), b_lo)
        b_hi = torch.where(c == 0, torch.where(b_ok, inf, -inf), b_hi)
        lo, hi = torch.maximum(a_lo, b_lo), torch.minimum(a_hi, b_hi)  # dy range [m]
        # columns whose centres lie in [lo, hi] across the road, clipped to the picture
        col0 = 0.5 * v.width - 0.5 + rel[..., 1, None] / v.lateral_scale
        j0 = torch.ceil(col0 + lo / v.lateral_scale).clamp(min=0)
        j1 = torch.floor(col0 + hi / v.lateral_scale).clamp(max=v.width - 1)
        valid = (row <= last[..., None]) & (row >= 0) & (row < v.height) & (car_label >= 0)[..., None]
        run = torch.where(valid, j1 - j0, -1.0).long()  # [V, C, R] columns after the first (-1: none)
        n_cols = int(run.max()) + 1 if self.device.type == "cpu" else self._win_cols
        if n_cols <= 0:
            return
        start = base[:, None, None] + (row.long() * v.width + j0.long()).clamp(min=0)  # [V, C, R]
        q = self._cols_j[:n_cols]
        index = torch.where(q <= run[..., None], start[..., None] + q, flat.numel() - 1)  # [V, C, R, Q]
        shade = values[car_label.clamp(min=0)]  # [V, C]
        size = n_rows * n_cols
        for slot in range(car_label.shape[1]):  # in draw order; one car covers a pixel once
            flat.scatter_(0, index[:, slot].reshape(-1), shade[:, slot, None].expand(-1, size).reshape(-1))

    # ---------------------------------------------------------------- one view (reference env)
    def render(
        self,
        center: np.ndarray,
        vehicles: Sequence[CurvatureVehicle],
        target_lane: int | None = None,
        ego: CurvatureVehicle | None = None,
    ) -> np.ndarray:
        """Draw one scene around ``center`` (x, y) [m] with highway-env cars.

        Args:
            center: world point at the crop centre, usually a car's position.
            vehicles: cars to draw, each in the shade of its ``kind``; draw order is the
                sequence order.
            target_lane: lane painted in the target shade (when ``show_target_lane``).
            ego: the car whose view this is, drawn in the 'agent' shade. When it is not the
                agent, the agent is drawn as a 'learned' car: to a car driven by a copy of
                the agent, the agent is another learning driver.

        Returns:
            ``(H, W, 3)`` uint8 RGB picture, or ``(H, W)`` grayscale when ``channels == 1``.
        """
        f64 = dict(dtype=torch.float64, device=self.device)
        rows = [[c.position[0], c.position[1], c.heading] for c in vehicles]
        cars = torch.tensor(rows, **f64).view(1, -1, 3)
        kinds = [("agent" if c is ego else ("learned" if c.kind == "agent" else c.kind)) for c in vehicles]
        labels = torch.tensor([[LABEL[k] for k in kinds]], dtype=torch.long, device=self.device).view(1, -1)
        path = None
        if ego is not None and self.path_length > 0:
            path = torch.tensor([[ego.position[0], ego.position[1], ego.heading, ego.curvature]], **f64)
        img = self.render_batch(
            torch.tensor([[float(center[0]), float(center[1])]], **f64),
            torch.tensor([-1 if target_lane is None else int(target_lane)], device=self.device),
            cars, labels, path)
        return img[0].cpu().numpy()

    def to_pixels(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map world points ``[..., (x, y)]`` [m] to continuous pixel coordinates ``(col, row)``."""
        v = self.view
        col = 0.5 * v.width + (points[..., 1] - center[1]) / v.lateral_scale
        row = 0.5 * v.height - (points[..., 0] - center[0]) / v.longitudinal_scale
        return np.stack([col, row], axis=-1)

    def path_points(self, car: CurvatureVehicle) -> np.ndarray:
        """``[S, (x, y)]`` [m]: the points of the arc ``car`` drives over ``path_length`` metres
        at its current heading and curvature, as drawn."""
        state = torch.tensor([car.position[0], car.position[1], car.heading, car.curvature],
                             dtype=torch.float64, device=self.device)
        return arc_points(state, self._path_s).cpu().numpy()

    car_corners = staticmethod(car_corners)
