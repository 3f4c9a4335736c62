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
(spaced under half a pixel along the arc) falls in; every car's path (``path_time``) is a few
chords of its arc, each a 1-px line (:mod:`memrl.envs.render_paths`).

Draw order: the road, then (``path_time > 0``) every car's path (later slots over earlier
ones), then the cars, then (``path_length > 0``) the viewing car's path cue.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from memrl.envs.render_paths import chord_count, paint_paths
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


class _Ops:
    """The few array operations the rasterizer needs, on numpy arrays or torch tensors."""

    # Hand-written: one rasterizer must run on numpy (the reference env's single views, where
    # torch's per-call overhead would triple the env's step time) and on torch (the batched
    # engine, any device); arithmetic and indexing are written once, these few calls differ.
    ceil: Any
    floor: Any
    where: Any
    minimum: Any
    maximum: Any
    cos: Any
    sin: Any
    amax: Any

    def __init__(self, xp: Any) -> None:
        self.is_torch = xp is torch
        self.inf = np.float32(np.inf) if not self.is_torch else torch.tensor(np.inf, dtype=torch.float32)
        for name in ("ceil", "floor", "where", "minimum", "maximum", "cos", "sin", "amax"):
            setattr(self, name, getattr(xp, name))

    def f32(self, x: Any) -> Any:
        return x.to(torch.float32) if self.is_torch else x.astype(np.float32)

    def f64(self, x: Any) -> Any:
        return x.to(torch.float64) if self.is_torch else x.astype(np.float64)

    def i64(self, x: Any) -> Any:
        return x.long() if self.is_torch else x.astype(np.int64)

    def clip(self, x: Any, low: float | None, high: float | None) -> Any:
        return torch.clamp(x, min=low, max=high) if self.is_torch else np.clip(x, low, high)

    def stack(self, items: list[Any], axis: int) -> Any:
        return torch.stack(items, dim=axis) if self.is_torch else np.stack(items, axis=axis)

    def cat(self, items: list[Any], axis: int) -> Any:
        return torch.cat(items, dim=axis) if self.is_torch else np.concatenate(items, axis=axis)

    def cumsum(self, x: Any, axis: int) -> Any:
        return torch.cumsum(x, dim=axis) if self.is_torch else np.cumsum(x, axis=axis)

    def repeat(self, x: Any, n: int) -> Any:
        """Each element ``n`` times, in order."""
        return x.repeat_interleave(n) if self.is_torch else np.repeat(x, n)

    def add_at(self, a: Any, index: tuple[Any, Any], value: int) -> None:
        if self.is_torch:
            a.index_put_(index, torch.full_like(index[0], value, dtype=a.dtype), accumulate=True)
        else:
            np.add.at(a, index, value)

    def slot_major(self, x: Any) -> Any:
        """``x`` with its first two axes swapped, laid out contiguously."""
        return x.transpose(0, 1).contiguous() if self.is_torch else np.ascontiguousarray(x.swapaxes(0, 1))

    def take_rows(self, source: Any, index: Any, out: Any) -> None:
        """``out[i] = source[index[i]]`` for rows, written straight into ``out``."""
        if not self.is_torch:  # torch's row gather beats np.take: run it on the same memory
            source, index, out = torch.from_numpy(source), torch.from_numpy(index), torch.from_numpy(out)
        torch.index_select(source, 0, index, out=out)

    def zeros(self, shape: tuple[int, ...], like: Any) -> Any:
        if self.is_torch:
            return torch.zeros(shape, dtype=like.dtype, device=like.device)
        return np.zeros(shape, dtype=like.dtype)

    def asarray(self, values: list[float], like: Any) -> Any:
        """A 1-D array of ``values`` with ``like``'s dtype (and device)."""
        if self.is_torch:
            return torch.tensor(values, dtype=like.dtype, device=like.device)
        return np.asarray(values, dtype=like.dtype)

    def arange(self, n: int, device: torch.device) -> Any:
        return torch.arange(n, device=device) if self.is_torch else np.arange(n)

    def nonzero(self, x: Any) -> tuple[Any, ...]:
        """Indices of the true elements of ``x``, one array per axis, in C order."""
        return torch.nonzero(x, as_tuple=True) if self.is_torch else np.nonzero(x)

    def searchsorted(self, sorted_: Any, values: Any) -> Any:
        """Where ``values`` would go in the ascending ``sorted_`` (the first place)."""
        return torch.searchsorted(sorted_, values) if self.is_torch else np.searchsorted(sorted_, values)

    def flip0(self, x: Any) -> Any:
        """``x`` reversed along its first axis."""
        return x.flip(0) if self.is_torch else x[::-1]

    def transpose(self, x: Any) -> Any:
        """A 2-D ``x`` transposed (a view)."""
        return x.T

    def segment_max(self, x: Any, bounds: list[int]) -> Any:
        """The largest element of each run ``x[bounds[i]:bounds[i + 1]]`` (-1 where empty)."""
        if not self.is_torch:
            lo = np.asarray(bounds[:-1])
            full = np.diff(bounds) > 0
            out = np.full(len(lo), -1.0, dtype=x.dtype)
            out[full] = np.maximum.reduceat(x, lo[full])
            return out
        return torch.stack([x[a:b].amax() if b > a else x.new_tensor(-1.0)
                            for a, b in zip(bounds[:-1], bounds[1:], strict=True)])

    def size(self, x: Any) -> int:
        """Elements of ``x``."""
        return x.numel() if self.is_torch else x.size

    def empty_u8(self, n: int, device: torch.device) -> Any:
        return torch.empty(n, dtype=torch.uint8, device=device) if self.is_torch else np.empty(n, np.uint8)


NUMPY, TORCH = _Ops(np), _Ops(torch)
_CORNER_SIGNS = ((-1, -1), (-1, 1), (1, 1), (1, -1))  # highway-env's polygon order


def body_corners(x: Any, y: Any, heading: Any, length: float, width: float) -> Any:
    """Body corners ``[..., 4, (x, y)]`` [m] of cars at (x, y) [m] with ``heading`` [rad], for
    numpy arrays or torch tensors ``[...]`` (the reference env and the batched engine)."""
    x_ = TORCH if isinstance(x, torch.Tensor) else NUMPY
    cos, sin = x_.cos(heading)[..., None], x_.sin(heading)[..., None]
    lx = x_.asarray([0.5 * length * a for a, _ in _CORNER_SIGNS], like=cos)
    ly = x_.asarray([0.5 * width * b for _, b in _CORNER_SIGNS], like=cos)
    return x_.stack([lx * cos - ly * sin + x[..., None], lx * sin + ly * cos + y[..., None]], axis=-1)


def car_corners(vehicles: Sequence[CurvatureVehicle]) -> np.ndarray:
    """Body corners ``[N, 4, (x, y)]`` [m] of highway-env cars (all of one size)."""
    state = np.array([[c.position[0], c.position[1], c.heading] for c in vehicles], dtype=np.float64)
    state = state.reshape(-1, 3)
    car = vehicles[0] if vehicles else None
    length, width = (car.LENGTH, car.WIDTH) if car is not None else (0.0, 0.0)
    return body_corners(state[:, 0], state[:, 1], state[:, 2], length, width)


def arc_points(state: Any, s: Any) -> Any:
    """Points ``[..., S, (x, y)]`` [m] at arc lengths ``s`` [S] along the arcs that cars with
    ``state [..., (x, y, heading, curvature)]`` drive at constant curvature (numpy or torch)."""
    x_ = TORCH if isinstance(state, torch.Tensor) else NUMPY
    x, y, h, k = (state[..., i, None] for i in range(4))
    straight = abs(k) < 1e-9
    k_safe = x_.where(straight, 1.0, k)
    dx = x_.where(straight, s * x_.cos(h), (x_.sin(h + k * s) - x_.sin(h)) / k_safe)
    dy = x_.where(straight, s * x_.sin(h), (x_.cos(h) - x_.cos(h + k * s)) / k_safe)
    return x_.stack([x + dx, y + dy], axis=-1)


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
            heading and curvature, over the cars (0: none).
        path_time: every car's path drawn ahead of it at its current heading and curvature
            over ``speed * path_time`` metres [s], under the cars, each in its car's shade
            (0: none; not together with ``path_length``).
        max_speed: the highest speed a car can have [m/s]: with ``max_curvature``, fixes the
            chords per path (``path_time > 0``; fixed shapes).
        max_curvature: the highest |curvature| a car can have [rad/m]: each path is drawn as
            chords few enough to stray at most half a pixel across from its arc at this
            curvature on the longest path (0: one chord, straight paths only).
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
        path_time: float = 0.0,
        max_speed: float = 0.0,
        max_curvature: float = 0.0,
        palette: dict[str, tuple[int, int, int]] | None = None,
        channels: int = 3,
        device: torch.device | str = "cpu",
    ) -> None:
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels}")
        if path_length > 0 and path_time > 0:
            raise ValueError(f"path_length ({path_length}) and path_time ({path_time}) are two path "
                             "cues: set one of them to 0")
        self.view, self.channels, self.device = view, channels, torch.device(device)
        self.lanes_count, self.lane_width = lanes_count, lane_width
        self.car_length, self.car_width = float(car_size[0]), float(car_size[1])
        self.show_target_lane, self.dash_length, self.path_length = show_target_lane, dash_length, path_length
        self.path_time = path_time
        rgb = dict(PALETTE if palette is None else palette)
        shades = [rgb[name] for name in LABELS]
        if channels == 3:
            table = np.array(shades, dtype=np.uint8)  # [K, 3]
        else:
            gray = gray_palette(dict(zip(LABELS, shades, strict=True)))
            table = np.array([gray[n] for n in LABELS], dtype=np.uint8)
        self.palette = {n: (tuple(shades[i]) if channels == 3 else int(table[i]))
                        for i, n in enumerate(LABELS)}
        h, w = view.height, view.width
        half_diag = 0.5 * math.hypot(self.car_length, self.car_width)
        # largest window a car needs at any heading [px] (fixed shapes on accelerators)
        self._win_rows = math.ceil(2 * half_diag / view.longitudinal_scale) + 3
        self._win_cols = math.ceil(2 * half_diag / view.lateral_scale) + 3
        self._half_span = 0.5 * h * view.longitudinal_scale  # [m] shown ahead and behind
        line = max(view.lateral_scale, 0.15)
        step = 0.5 * min(view.lateral_scale, view.longitudinal_scale)
        left, right = -0.5 * lane_width, (lanes_count - 0.5) * lane_width
        consts = {
            "table": table,
            "labels": np.arange(len(LABELS), dtype=np.uint8),
            "win_i": np.arange(max(self._win_rows, h), dtype=np.float32),
            "cols": np.arange(max(w, self._win_cols), dtype=np.int64),
            "rows": np.arange(h, dtype=np.int64)[None, :],
            "dividers": (np.arange(1, lanes_count) - 0.5) * lane_width,
            # world bands across the road [m]: the road, its left and right edge markings
            "road_bands": np.array([left, right, left, left + line, right - line, right]),
            "lane_half": np.array([-0.5 * lane_width, 0.5 * lane_width]),
            # columns per divider band
            "div_k": np.arange(math.ceil(line / view.lateral_scale) + 1, dtype=np.float64),
            # dashes that can show in a crop: 2 * half_span of road plus a period on each side
            "dash_k": np.arange(math.ceil(2 * self._half_span / (2 * dash_length)) + 3, dtype=np.float64),
            "path_s": np.linspace(0.0, path_length, max(2, math.ceil(path_length / step) + 1)),
        }
        # every car's path: chords of its arc; the most pixels a chord steps through (fixed shapes)
        longest, fine = max_speed * path_time, min(view.lateral_scale, view.longitudinal_scale)
        self._chords = chord_count(longest, max_curvature, 0.5 * fine)  # each within half a pixel
        self._chord_steps = math.ceil(longest / self._chords / fine) + 2
        consts["chord_i"] = np.arange(max(self._chord_steps, h, w), dtype=np.float32)
        on_device = {k: torch.from_numpy(v).to(self.device) for k, v in consts.items()}
        self._consts: dict[_Ops, dict[str, Any]] = {NUMPY: consts, TORCH: on_device}
        self.table = self._consts[TORCH]["table"]

    # ------------------------------------------------------------------------ batched
    def render_batch(self, center: Any, target_lane: Any, cars: Any, car_label: Any, path: Any = None) -> Any:
        """Pictures ``[V, H, W]`` (grayscale) or ``[V, H, W, 3]`` (RGB) of ``V`` views, as numpy
        arrays or torch tensors (on the renderer's device) like the arguments.

        Args:
            center: ``[V, 2]`` world point (x, y) [m] at each crop's centre (float64).
            target_lane: ``[V]`` lane painted in the target shade (-1: none).
            cars: ``[V, C, 3]`` (x, y, heading) of the cars to draw, in draw order (float64).
            car_label: ``[V, C]`` index into :data:`LABELS` of each car (-1: no car in that slot).
            path: when ``path_length > 0``, ``[V, 4]`` (x, y, heading, curvature) of each
                view's own car, whose path is drawn; when ``path_time > 0``, ``[V, C, 5]``
                (x, y, heading, curvature, speed) of the cars in ``cars``, whose paths are
                drawn in their ``car_label`` shades (None: no path).
        """
        v, x_ = self.view, TORCH if isinstance(center, torch.Tensor) else NUMPY
        flat = x_.empty_u8(len(center) * v.height * v.width + 1, self.device)
        self.render_into(flat, 0, center, target_lane, cars, car_label, path)
        img = flat[:-1].reshape(len(center), v.height, v.width)
        return img if self.channels == 1 else self._consts[x_]["table"][x_.i64(img)]

    def render_into(self, flat: Any, start: int, center: Any, target_lane: Any, cars: Any, car_label: Any,
                    path: Any = None) -> None:
        """Draw the ``V`` pictures (labels when RGB) into ``flat[start : start + V * H * W]`` of a
        1-D uint8 buffer whose last element is spare (it takes the writes that fall outside a
        picture); arguments as :meth:`render_batch`."""
        v, x_ = self.view, TORCH if isinstance(center, torch.Tensor) else NUMPY
        k = self._consts[x_]
        n_views, size = len(center), v.height * v.width
        # Gray: paint the shades themselves; RGB: paint labels, then look their colours up.
        values = k["table"] if self.channels == 1 else k["labels"]
        base = start + x_.arange(n_views, self.device) * size  # [V] offset of each picture
        self._background(x_, center, target_lane, values, flat, base, start)
        if path is not None and self.path_time > 0:
            self._paint_paths(x_, flat, base, center, path, car_label, values)
        self._paint_cars(x_, flat, base, center, cars, car_label, values)
        if path is not None and self.path_length > 0:
            rel = arc_points(path, k["path_s"]) - center[:, None, :]  # [V, S, 2]
            col = x_.i64(x_.floor(0.5 * v.width + rel[..., 1] / v.lateral_scale))
            row = x_.i64(x_.floor(0.5 * v.height - rel[..., 0] / v.longitudinal_scale))
            ok = (row >= 0) & (row < v.height) & (col >= 0) & (col < v.width)
            index = x_.where(ok, base[:, None] + row * v.width + col, flat.shape[0] - 1)
            flat[index] = values[LABEL["agent"]]

    def _background(self, x_: _Ops, center: Any, target_lane: Any, values: Any, flat: Any, base: Any,
                    start: int) -> None:
        """Road, target lane and markings into the pictures: a shade per column, copied down
        every row, then the dashes of the lane dividers."""
        v, w, n, k = self.view, self.lane_width, self.lanes_count, self._consts[x_]
        j, cy = k["cols"][: v.width], center[:, 1:2]

        def edges(y: Any) -> Any:
            """The first column whose centre lies at or beyond world y across the road."""
            return x_.ceil(0.5 * v.width + (y - cy) / v.lateral_scale - 0.5)

        def bands(y: Any) -> Any:
            """[V, B, W]: columns whose centres lie in the world bands [y[2b], y[2b + 1]) across
            the road, for bounds ``y`` [B * 2] or [V, B * 2]."""
            e = edges(y)
            return (j >= e[:, 0::2, None]) & (j < e[:, 1::2, None])

        # the road, then its two edge markings
        road = bands(k["road_bands"])  # [V, 3, W]
        col = x_.where(road[:, 0], values[LABEL["road"]], values[LABEL["offroad"]])
        if self.show_target_lane:
            t = (x_.f64(target_lane) * w)[:, None] + k["lane_half"]  # [V, 2] the lane's bounds
            col = x_.where(bands(t)[:, 0] & (target_lane[:, None] >= 0), values[LABEL["target_lane"]], col)
        col = x_.where(road[:, 1] | road[:, 2], values[LABEL["marking"]], col)
        line = max(v.lateral_scale, 0.15)  # markings: at least 1 px, at most 0.15 m wide
        n_views = len(center)
        pictures = flat[start: start + n_views * v.height * v.width].reshape(n_views, v.height, v.width)
        if n < 2:
            pictures[:] = col[:, None, :]
            return
        # dash k covers [s_k, s_k + L] along the road, s_k = first + k * period: rows [r0, r1)
        period = 2.0 * self.dash_length
        x_top = center[:, 0:1] + 0.5 * v.height * v.longitudinal_scale
        first = x_.floor((x_top - 2 * self._half_span) / period) * period - period
        starts = first + k["dash_k"] * period  # [V, K]
        cx, lon = center[:, 0:1], v.longitudinal_scale
        r0 = x_.ceil(0.5 * v.height - (starts + self.dash_length - cx) / lon - 0.5)
        r1 = x_.ceil(0.5 * v.height - (starts - cx) / lon - 0.5)
        r0, r1 = x_.i64(x_.clip(r0, 0, v.height)), x_.i64(x_.clip(r1, 0, v.height))
        # +1 where a dash starts, -1 where it ends, summed down the picture
        count = x_.zeros((n_views, v.height + 1), like=r0)
        views = x_.arange(n_views, self.device)[:, None]
        x_.add_at(count, (views + r0 * 0, r0), 1)
        x_.add_at(count, (views + r0 * 0, r1), -1)
        dash = x_.cumsum(count[:, :-1], axis=1) > 0  # [V, H]
        # the divider columns: those of the bands [yd - line/2, yd + line/2), at most a few each
        yd = k["dividers"] - 0.5 * line  # [D]
        a, b = edges(yd), edges(yd + line)  # [V, D]
        cols = x_.i64(a[..., None] + k["div_k"])  # [V, D, k]
        ok = (cols < b[..., None]) & (cols >= 0) & (cols < v.width)
        # two rows per view, [plain, dashed] (+ a spare column for the columns not drawn), and
        # every picture row copied from one of them in one gather
        rows = x_.zeros((n_views, 2, v.width + 1), like=col)
        rows[:, :, : v.width] = col[:, None, :]
        dashed = x_.where(ok, cols, v.width).reshape(n_views, -1) + (2 * views + 1) * (v.width + 1)
        rows.reshape(-1)[dashed.reshape(-1)] = values[LABEL["marking"]]
        source = rows[:, :, : v.width].reshape(2 * n_views, v.width)
        x_.take_rows(source, (2 * views + dash).reshape(-1), pictures.reshape(-1, v.width))

    def _paint_paths(self, x_: _Ops, flat: Any, base: Any, center: Any, path: Any, car_label: Any,
                     values: Any) -> None:
        """Paint every car's path (``path_time > 0``): the arc it drives at its heading and
        curvature over ``speed * path_time`` metres, as a few chords, each a 1-px line in its
        car's shade, slot after slot (one shade per write: later cars' paths over earlier ones,
        as the cars)."""
        if car_label.shape[1] == 0:
            return
        dynamic = not x_.is_torch or self.device.type == "cpu"  # else fixed shapes: no host sync
        paint_paths(x_, flat, base, center, path, car_label, values, self.view, self.path_time, self._chords,
                    None if dynamic else self._chord_steps, self._consts[x_]["chord_i"])

    def _paint_cars(self, x_: _Ops, flat: Any, base: Any, center: Any, cars: Any, car_label: Any,
                    values: Any) -> None:
        """Paint each car over the pixels whose centres its body covers, slot after slot
        (later cars over earlier ones): per picture row, the run of columns inside the body."""
        v, k = self.view, self._consts[x_]
        if car_label.shape[1] == 0:
            return
        # slot-major [C, V, ...]: each slot's pixels lie together for its own write below
        cars, car_label = x_.slot_major(cars), x_.slot_major(car_label)
        base = base[:, None]  # [V, 1] against [C, V, R]
        rel = x_.f32(cars[..., :2] - center[None, :, :])  # [C, V, 2] car from view centre [m]
        cos, sin = x_.f32(x_.cos(cars[..., 2])), x_.f32(x_.sin(cars[..., 2]))
        half_len, half_wid = 0.5 * self.car_length, 0.5 * self.car_width
        # rows whose centres lie within the body's extent along the road
        half_x = half_len * abs(cos) + half_wid * abs(sin)  # [m]
        row_c = 0.5 * v.height - rel[..., 0] / v.longitudinal_scale  # car centre [continuous px]
        first = x_.ceil(row_c - half_x / v.longitudinal_scale - 0.5)
        last = x_.floor(row_c + half_x / v.longitudinal_scale - 0.5)
        dynamic = not x_.is_torch or self.device.type == "cpu"  # else fixed shapes: no host sync
        n_rows = int((last - first).max()) + 1 if dynamic else self._win_rows
        if n_rows <= 0:
            return
        row = first[..., None] + k["win_i"][:n_rows]  # [C, V, R]
        dx = (0.5 * v.height - 0.5 - row) * v.longitudinal_scale - rel[..., 0, None]  # row centre - car [m]
        c, s = cos[..., None], sin[..., None]
        # |dx c + dy s| <= L/2 and |dy c - dx s| <= W/2, solved for dy on each row
        inf = x_.inf
        s_safe, c_safe = s + (s == 0), c + (c == 0)  # 1 where 0 (that branch is not used)
        a0, a1 = (-half_len - dx * c) / s_safe, (half_len - dx * c) / s_safe
        a_ok = abs(dx * c) <= half_len
        a_lo = x_.where(s == 0, x_.where(a_ok, -inf, inf), x_.minimum(a0, a1))
        a_hi = x_.where(s == 0, x_.where(a_ok, inf, -inf), x_.maximum(a0, a1))
        b0, b1 = (-half_wid + dx * s) / c_safe, (half_wid + dx * s) / c_safe
        b_ok = abs(dx * s) <= half_wid
        b_lo = x_.where(c == 0, x_.where(b_ok, -inf, inf), x_.minimum(b0, b1))
        b_hi = x_.where(c == 0, x_.where(b_ok, inf, -inf), x_.maximum(b0, b1))
        lo, hi = x_.maximum(a_lo, b_lo), x_.minimum(a_hi, b_hi)  # dy range [m]
        # columns whose centres lie in [lo, hi] across the road, clipped to the picture
        col0 = 0.5 * v.width - 0.5 + rel[..., 1, None] / v.lateral_scale
        j0 = x_.clip(x_.ceil(col0 + lo / v.lateral_scale), 0, v.width)  # finite, and empty stays empty
        j1 = x_.clip(x_.floor(col0 + hi / v.lateral_scale), -1, v.width - 1)
        valid = (row <= last[..., None]) & (row >= 0) & (row < v.height) & (car_label >= 0)[..., None]
        run = x_.where(valid, x_.i64(j1 - j0), -1)  # [C, V, R] columns after the first (-1: none)
        # rows with no pixel write to the spare element; the window's columns past a row's run
        # repeat the run's last pixel (the same car, the same shade: written twice, no harm)
        start = x_.where(run >= 0, base + x_.i64(row) * v.width + x_.i64(j0), flat.shape[0] - 1)
        shade = values[x_.clip(car_label, 0, None)]  # [C, V]
        # a window as wide as the slot's widest run (on CPU; else fixed: no host sync)
        widths = ([int(r) + 1 for r in x_.amax(run.reshape(len(run), -1), 1).tolist()] if dynamic
                  else [self._win_cols] * len(run))
        run = x_.clip(run, 0, None)
        for slot, width in enumerate(widths):  # in draw order; one car covers a pixel once
            if width <= 0:
                continue
            index = start[slot][..., None] + x_.minimum(k["cols"][:width], run[slot][..., None])  # [V, R, Q]
            flat[index.reshape(-1)] = x_.repeat(shade[slot], n_rows * width)

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
                the agent, the agent is another learning driver. Its path is drawn when
                ``path_length > 0``; with ``path_time > 0`` every car's path is drawn, each in
                its car's shade.

        Returns:
            ``(H, W, 3)`` uint8 RGB picture, or ``(H, W)`` grayscale when ``channels == 1``.
        """
        # numpy: a single view costs a few hundred microseconds, a third of torch's per-call overhead
        cars = np.array([[c.position[0], c.position[1], c.heading] for c in vehicles],
                        dtype=np.float64).reshape(1, -1, 3)
        kinds = [("agent" if c is ego else ("learned" if c.kind == "agent" else c.kind)) for c in vehicles]
        labels = np.array([LABEL[k] for k in kinds], dtype=np.int64).reshape(1, -1)
        path = None
        if ego is not None and self.path_length > 0:
            path = np.array([[ego.position[0], ego.position[1], ego.heading, ego.curvature]])
        elif self.path_time > 0:
            path = np.array([[c.position[0], c.position[1], c.heading, c.curvature, c.speed]
                             for c in vehicles], dtype=np.float64).reshape(1, -1, 5)
        img = self.render_batch(np.array([[float(center[0]), float(center[1])]]),
                                np.array([-1 if target_lane is None else int(target_lane)]), cars, labels,
                                path)
        return img[0]

    def to_pixels(self, center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map world points ``[..., (x, y)]`` [m] to continuous pixel coordinates ``(col, row)``."""
        v = self.view
        col = 0.5 * v.width + (points[..., 1] - center[1]) / v.lateral_scale
        row = 0.5 * v.height - (points[..., 0] - center[0]) / v.longitudinal_scale
        return np.stack([col, row], axis=-1)

    def path_points(self, car: CurvatureVehicle) -> np.ndarray:
        """``[S, (x, y)]`` [m]: the points of the arc ``car`` drives over ``path_length`` metres
        at its current heading and curvature, as drawn."""
        state = np.array([car.position[0], car.position[1], car.heading, car.curvature])
        return arc_points(state, self._consts[NUMPY]["path_s"])

    car_corners = staticmethod(car_corners)
