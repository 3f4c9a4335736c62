"""Every car's path (``bev.path_time``) as a few straight strokes, for :class:`memrl.envs.render.BEVRenderer`.

A car's path is the arc it drives at its heading and curvature over ``speed * path_time``
metres. It is drawn as ``K`` chords of equal arc length, ``K`` fixed by the longest path and
the highest curvature so that no chord strays more than half a pixel across from its arc
(:func:`chord_count`); a straight path is one line. Each chord is a 1-px line (a DDA line, as
Bresenham's): stepping along the chord's major pixel axis (rows, or columns where it runs more
across the picture than along it), one pixel per row (column): the pixel holding the chord's
point nearest to that row's (column's) centre line (where the chord crosses it, else its end
in that row); and the pixel holding the path's end, its tip: where the car will be after
``path_time`` seconds at constant speed and curvature. Where two chords meet, each one's pixel
in the joint's row (column) lies within half a pixel of the joint, so the chords of a path join
into one 8-connected line.

Cost: a path straight along the road (heading and curvature 0: every constant-speed car) is
one column of pixels, the rows from its car's to its tip's; with many paths to draw
(:data:`MANY`, on the CPU) those are drawn as such runs, the others as chords, and only the
paths that can reach their picture at all: the same pixels as chords everywhere
(``tests/test_render_paths.py``), at a fraction of the arithmetic.

Hand-written (no library rasterizes many small lines into many pictures at once): the same
arithmetic on numpy arrays and torch tensors (the renderer's two paths), slot after slot in
draw order (later cars' paths over earlier ones, as the cars).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

SMALL = 1 << 15
"""Steps of all chords (rows of all column runs) at most that :func:`paint_paths` takes in one
pass (more: per run of layers with equal windows); the same pixels either way."""
MANY = 64
"""Paths (views x car slots) from which :func:`paint_paths` draws only those that can show and
those along the road as column runs (on the CPU); the same pixels either way."""
Steps = dict[int, list[tuple[Any, int, int, Any]]]
"""Per layer (run of car slots drawn in one write): offsets in the pictures' buffer (the spare
element: none) of the pixels of paths ``lo:hi``, ``[paths, ...]`` with as many per path (count
None), or 1-D, path after path, ``count [paths]`` of each."""


def chord_count(max_length: float, max_curvature: float, tolerance: float) -> int:
    """Chords per path: the fewest whose sagitta ``k l^2 / 8`` (the chord's largest distance
    from its arc of length ``l`` at curvature ``k``) stays within ``tolerance`` [m] on the
    longest path ``max_length`` [m] at the highest curvature ``max_curvature`` [rad/m]."""
    return max(1, math.ceil(max_length * math.sqrt(max_curvature / (8.0 * tolerance))))


def chord_points(x: Any, y: Any, heading: Any, curvature: Any, length: Any, chords: int) -> tuple[Any, Any]:
    """x and y ``[K + 1, ...]`` [m] of the points at arc lengths ``length * j / K`` along the
    arcs that cars at ``(x, y)`` with ``heading`` and ``curvature`` drive (arrays ``[...]``,
    numpy or torch; ``length`` [m]). Chord j runs at heading ``h + k l (j + 1/2)`` and is
    ``l sinc(k l / 2)`` long (``l = length / K``): the heading turns by ``k l`` from chord to
    chord (a rotation, no further sines); a straight path's chords all run at its heading."""
    torch_ = isinstance(x, torch.Tensor)
    xp: Any = torch if torch_ else np
    step = length / chords  # arc length of a chord [m]
    turn = curvature * step  # heading change per chord [rad]
    chord = step * xp.sinc(turn / (2 * math.pi))  # numpy's and torch's sinc: sin(pi u) / (pi u)
    # x and y side by side: the chord's direction (c, s) turns to (c cw - s sw, s cw + c sw)
    direction = xp.stack([xp.cos(heading + 0.5 * turn), xp.sin(heading + 0.5 * turn)])
    cw, sw = xp.cos(turn), xp.sin(turn)
    across = xp.stack([-sw, sw])  # times the swapped (s, c)
    points = xp.empty((chords + 1, 2, *direction.shape[1:]), dtype=direction.dtype,
                      **({"device": direction.device} if torch_ else {}))
    points[0, 0], points[0, 1] = x, y
    for j in range(chords):
        xp.add(points[j], chord * direction, out=points[j + 1])
        if j + 1 < chords:
            direction = direction * cw + (direction.flip(0) if torch_ else direction[::-1]) * across
    return points[:, 0], points[:, 1]


def paint_paths(x_: Any, flat: Any, base: Any, center: Any, path: Any, label: Any, values: Any, view: Any,
                path_time: float, chords: int, steps: int | None, index_i: Any) -> None:
    """Paint every car's path, slot after slot (later slots' paths over earlier ones).

    Args:
        x_: the renderer's array operations (numpy or torch).
        flat: the pictures' 1-D uint8 buffer, its last element spare.
        base: ``[V]`` offset of each picture in ``flat``.
        center: ``[V, 2]`` world point at each picture's centre [m].
        path: ``[V, C, 5]`` (x, y, heading, curvature, speed) of the cars.
        label: ``[V, C]`` each car's shade index (-1: no car).
        values: the value written for each shade index.
        view: the pictures' size and scales.
        path_time: [s]; each path is ``speed * path_time`` long.
        chords: chords per path.
        steps: pixels per chord (fixed shapes: no host sync); None: as many as the longest
            chord needs (CPU).
        index_i: float32 ``arange`` at least as long as a picture's side and any chord's steps.
    """
    n_views, n_slots = label.shape
    spare, parts = flat.shape[0] - 1, []
    if steps is None and n_views * n_slots >= MANY:
        length = path[..., 4] * path_time  # [V, C] [m]
        # a path lies within its length of its car: those farther off the picture draw nothing
        reach_x = 0.5 * view.height * view.longitudinal_scale + 1.0 + length
        reach_y = 0.5 * view.width * view.lateral_scale + 1.0 + length
        ok = ((label >= 0) & (abs(path[..., 0] - center[:, None, 0]) <= reach_x)
              & (abs(path[..., 1] - center[:, None, 1]) <= reach_y))
        along = ok & (path[..., 2] == 0) & (path[..., 3] == 0)  # straight along the road
        # consecutive slots of the same shade in every view are one layer: where their paths
        # cross, either order paints the same
        by_slot = x_.slot_major(label)
        same = (by_slot[1:] == by_slot[:-1]).all(1).tolist()
        layers = [0, *(c for c in range(1, n_slots) if not same[c - 1])]
        starts = x_.asarray([*layers, n_slots], like=label)
        for chosen in (along, ok & ~along):
            slot_i, view_i = x_.nonzero(x_.transpose(chosen))  # slot-major: in draw order
            if len(view_i):
                bounds = x_.searchsorted(slot_i, starts).tolist()  # each layer's paths
                rows, at = path[view_i, slot_i], (center[view_i], base[view_i])  # [M, 5], their views
                if chosen is along:
                    pixels = _column_runs(x_, rows, *at, view, path_time, chords, bounds)
                else:
                    pixels = _chord_lines(x_, rows, *at, None, view, path_time, chords, spare, bounds, None,
                                          index_i)
                parts.append((pixels, values[label[view_i, slot_i]]))
    else:  # every (slot, view) pair, slot-major, the absent masked
        layers = list(range(n_slots))
        rows = x_.slot_major(path).reshape(-1, 5)  # [C * V, 5]
        shown = x_.slot_major(label).reshape(-1)
        dev = base.device if x_.is_torch else None
        view_i = x_.arange(n_slots * n_views, dev) % n_views
        bounds = [c * n_views for c in range(n_slots + 1)]
        pixels = _chord_lines(x_, rows, center[view_i], base[view_i], shown >= 0, view, path_time, chords,
                              spare, bounds, steps, index_i)
        parts.append((pixels, values[x_.clip(shown, 0, None)]))
    for c in range(len(layers)):  # in draw order
        for pixels, shade in parts:
            for index, lo, hi, count in pixels.get(c, ()):  # index [paths lo:hi, ...] (count: 1-D)
                # one shade (checked on the CPU only: on an accelerator it would sync the host)
                if hi - lo == 1 or (steps is None and bool((shade[lo:hi] == shade[lo]).all())):
                    flat[index.reshape(-1)] = shade[lo]
                else:
                    flat[index.reshape(-1)] = x_.repeat(shade[lo:hi], x_.size(index[0]) if count is None
                                                        else count)


def _passes(x_: Any, need: Any, bounds: list[int], per_step: int) -> list[tuple[int, int, int]]:
    """Runs ``(first layer, end layer, steps)`` of layers drawn in one pass, for lines (column
    runs or chords) that need ``need + 1`` steps ``[M]`` (``bounds``: each layer's lines;
    ``per_step``: elements per line and step): all layers at the most steps any needs while
    that is small (fresh large arrays cost page faults, many small ones a call each), else runs
    of layers with equal needs."""
    n_layers = len(bounds) - 1
    if bounds[-1] == 0:
        return []
    most = int(x_.amax(need, 0)) + 1
    if most * bounds[-1] * per_step <= SMALL:
        return [(0, n_layers, most)]
    widths = [int(w) + 1 for w in x_.segment_max(need, bounds).tolist()]
    out, start = [], 0
    while start < n_layers:
        end = start + 1
        while end < n_layers and widths[end] == widths[start]:
            end += 1
        out.append((start, end, widths[start]))
        start = end
    return out


def _split(out: Steps, index: Any, bounds: list[int], start: int, end: int) -> None:
    """Hand each layer in ``start:end`` its rows of ``index`` (paths ``bounds[start]:bounds[end]``)."""
    first = bounds[start]
    for c in range(start, end):
        lo, hi = bounds[c], bounds[c + 1]
        if hi > lo:
            out.setdefault(c, []).append((index[lo - first: hi - first], lo, hi, None))


def _column_runs(x_: Any, rows: Any, center: Any, base: Any, view: Any, path_time: float, chords: int,
                 bounds: list[int]) -> Steps:
    """The pixels of the paths of cars straight along the road (heading and curvature 0),
    ``rows [M, 5]``, in their pictures (centred at ``center [M, 2]``, at ``base [M]`` in the
    buffer; ``bounds``: each layer's paths): each a run of rows in one column, the pixels its
    chords' DDA lines and its tip hold."""
    rel = rows[:, :2] - center
    # the tip summed chord by chord, as chord_points does: the same tip row
    tip, step = rel[:, 0], rows[:, 4] * path_time / chords
    for _ in range(chords):
        tip = tip + step
    lon = view.longitudinal_scale
    col = x_.floor(0.5 * view.width + x_.f32(rel[:, 1]) / view.lateral_scale)
    top = x_.clip(x_.floor(0.5 * view.height - x_.f32(tip) / lon), 0.0, None)
    bottom = x_.clip(x_.floor(0.5 * view.height - x_.f32(rel[:, 0]) / lon), None, view.height - 1.0)
    # the rows of each run (0: none), from its top down: exactly its pixels, no spare writes
    count = x_.i64(x_.where((col >= 0) & (col < view.width) & (bottom >= top), bottom - top + 1, 0.0))
    # [M + 1] where each run's pixels start when all runs' pixels are laid end to end
    first = x_.cat([count[:1] * 0, x_.cumsum(count, 0)], 0)
    ends = first[bounds].tolist()  # each layer's
    if ends[-1] == 0:
        return {}
    # pixel p of run r: start_r + (p - first_r) * width, as one repeat and one arange
    start = x_.i64(top * view.width + col) + base - first[:-1] * view.width
    index = x_.repeat(start, count) + x_.arange(ends[-1], base.device if x_.is_torch else None) * view.width
    out: Steps = {}
    for c, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        if ends[c + 1] > ends[c]:
            out[c] = [(index[ends[c]: ends[c + 1]], lo, hi, count[lo:hi])]
    return out


def _chord_lines(x_: Any, rows: Any, center: Any, base: Any, ok: Any, view: Any, path_time: float,
                 chords: int, spare: int, bounds: list[int], steps: int | None, index_i: Any) -> Steps:
    """The pixels of the paths of cars ``rows [M, 5]`` in their pictures (as
    :func:`_column_runs`; ``ok [M]``: drawn, None: all) as chords, each a 1-px DDA line (module
    doc), and their tips: ``steps`` per chord, or (None) as many as the layer's longest chord
    needs (``index_i``: as :func:`paint_paths`)."""
    height, width = view.height, view.width
    rel = rows[:, :2] - center
    xs, ys = chord_points(rel[:, 0], rel[:, 1], rows[:, 2], rows[:, 3], rows[:, 4] * path_time, chords)
    # continuous pixel coordinates (row, col) [2, M, K + 1], as the cars'
    scale = x_.asarray([view.longitudinal_scale, view.lateral_scale], like=index_i)
    pixel = x_.f32(x_.stack([xs.T, ys.T], 0)) / scale[:, None, None]
    pixel = x_.asarray([0.5 * height, 0.5 * width], like=index_i)[:, None, None] + pixel * x_.asarray(
        [-1.0, 1.0], like=index_i)[:, None, None]
    # per chord [M, K]: the major axis (rows, or columns where it runs more across)
    p0, p1 = pixel[..., :-1], pixel[..., 1:]
    delta = abs(p1 - p0)
    by_row = delta[0] >= delta[1]
    ab0 = x_.where(by_row, p0, x_.flip0(p0))  # (major, minor) coordinate of its start
    ab1 = x_.where(by_row, p1, x_.flip0(p1))
    a0, b0 = ab0[0], ab0[1]
    lo, hi = x_.minimum(a0, ab1[0]), x_.maximum(a0, ab1[0])
    span = ab1 - ab0
    slope = span[1] / x_.where(span[0] == 0, 1.0, span[0])  # |slope| <= 1: at most 1 px per step
    side = x_.asarray([width, 1.0, height], like=index_i)  # float32: exact small integers below
    stride_major = x_.where(by_row, side[0], side[1])
    stride_minor = (width + 1) - stride_major
    if height == width:
        n_minor, end = width, width - 1.0
    else:
        n_minor, end = x_.where(by_row, side[0], side[2]), x_.where(by_row, side[2] - 1, side[0] - 1)
    # step i of a chord: the centre line of major pixel first + i, up to its last
    first = x_.clip(x_.floor(lo), 0.0, None) + 0.5
    last = (x_.clip(x_.floor(hi), None, end) if height == width else x_.minimum(x_.floor(hi), end)) + 0.5
    if ok is not None:
        last = x_.where(ok[:, None], last, -1.0)
    offset = x_.f64(base)[:, None] - 0.5 * stride_major  # pixel at centre * major + j * minor + offset
    # the pixel of each path's end, its tip
    tip = x_.floor(pixel[..., -1])  # [2, M]
    inside = (tip[0] >= 0) & (tip[0] < height) & (tip[1] >= 0) & (tip[1] < width)
    if ok is not None:
        inside = inside & ok
    tips = x_.where(inside, x_.i64(tip[0] * width + tip[1]) + base, spare)
    out: Steps = {c: [(tips[lo_:hi_], lo_, hi_, None)]
                  for c, (lo_, hi_) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)) if hi_ > lo_}
    passes = ([(0, len(bounds) - 1, steps)] if bounds[-1] else []) if steps is not None else \
        _passes(x_, (last - first).reshape(-1), [b * chords for b in bounds], 1)
    for start, stop, n in passes:
        part, i = slice(bounds[start], bounds[stop]), index_i[:n]
        centre = first[part, :, None] + i  # [paths, K, n]
        t = x_.minimum(x_.maximum(centre, lo[part, :, None]), hi[part, :, None])  # the nearest chord point
        j = x_.floor(b0[part, :, None] + (t - a0[part, :, None]) * slope[part, :, None])  # exact at the start
        draw = (centre <= last[part, :, None]) & (j >= 0) & (j < (n_minor if height == width else
                                                                    n_minor[part, :, None]))
        local = centre * stride_major[part, :, None] + j * stride_minor[part, :, None] + offset[part, :, None]
        _split(out, x_.i64(x_.where(draw, local, spare)), bounds, start, stop)
    return out
