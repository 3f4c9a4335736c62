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
"""Steps of all slots' chords at most that :func:`paint_polylines` takes in one pass (more: per
run of slots with equal windows); the same pixels either way."""


def chord_count(max_length: float, max_curvature: float, tolerance: float) -> int:
    """Chords per path: the fewest whose sagitta ``k l^2 / 8`` (the chord's largest distance
    from its arc of length ``l`` at curvature ``k``) stays within ``tolerance`` [m] on the
    longest path ``max_length`` [m] at the highest curvature ``max_curvature`` [rad/m]."""
    return max(1, math.ceil(max_length * math.sqrt(max_curvature / (8.0 * tolerance))))


def chord_points(x: Any, y: Any, heading: Any, curvature: Any, length: Any, chords: int) -> tuple[Any, Any]:
    """x and y ``[..., K + 1]`` [m] of the points at arc lengths ``length * j / K`` along the
    arcs that cars at ``(x, y)`` with ``heading`` and ``curvature`` drive (arrays ``[...]``,
    numpy or torch; ``length`` [m]). Chord j runs at heading ``h + k l (j + 1/2)`` and is
    ``l sinc(k l / 2)`` long (``l = length / K``): the heading turns by ``k l`` from chord to
    chord (a rotation, no further sines); a straight path's chords all run at its heading."""
    xp: Any = torch if isinstance(x, torch.Tensor) else np
    step = length / chords  # arc length of a chord [m]
    turn = curvature * step  # heading change per chord [rad]
    chord = step * xp.sinc(turn / (2 * math.pi))  # numpy's and torch's sinc: sin(pi u) / (pi u)
    c, s = xp.cos(heading + 0.5 * turn), xp.sin(heading + 0.5 * turn)
    cw, sw = xp.cos(turn), xp.sin(turn)
    xs, ys = [x], [y]
    for _ in range(chords):
        x, y = x + chord * c, y + chord * s
        xs.append(x)
        ys.append(y)
        c, s = c * cw - s * sw, s * cw + c * sw
    return xp.stack(xs, -1), xp.stack(ys, -1)


def paint_polylines(x_: Any, flat: Any, base: Any, col: Any, row: Any, ok: Any, shade: Any, height: int,
                    width: int, steps: int | None, index_i: Any) -> None:
    """Paint polylines as 1-px DDA lines (module doc), slot after slot.

    Args:
        x_: the renderer's array operations (numpy or torch).
        flat: the pictures' 1-D uint8 buffer, its last element spare.
        base: ``[V]`` offset of each picture in ``flat``.
        col, row: ``[C, V, P]`` float32 continuous pixel coordinates of each slot's and view's
            polyline vertices (slot-major: slot 0 drawn first).
        ok: ``[C, V]`` whether that polyline is drawn.
        shade: ``[C, V]`` the value written.
        height, width: picture size [px].
        steps: pixels per chord (fixed shapes: no host sync); None: as many as the longest
            chord needs (CPU).
        index_i: float32 ``arange`` at least as long as any chord's steps.
    """
    n_slots, n_points = col.shape[0], col.shape[-1]
    # per chord [C, V * K]
    c0, c1 = col[..., :-1].reshape(n_slots, -1), col[..., 1:].reshape(n_slots, -1)
    r0, r1 = row[..., :-1].reshape(n_slots, -1), row[..., 1:].reshape(n_slots, -1)
    by_row = abs(r1 - r0) >= abs(c1 - c0)  # step along rows (else along columns)
    a0, a1 = x_.where(by_row, r0, c0), x_.where(by_row, r1, c1)  # the major coordinate
    b0, b1 = x_.where(by_row, c0, r0), x_.where(by_row, c1, r1)  # the minor one
    lo, hi = x_.minimum(a0, a1), x_.maximum(a0, a1)
    span = a1 - a0
    slope = (b1 - b0) / x_.where(span == 0, 1.0, span)  # |slope| <= 1: at most 1 px per step
    rows = x_.f32(by_row)  # 1 where the chord steps along rows: exact integer arithmetic below
    n_minor = height + (width - height) * rows
    stride_major, stride_minor = 1 + (width - 1) * rows, width + (1 - width) * rows
    # step i of a chord: the centre line of major pixel first + i, up to its last
    drawn = x_.repeat(ok.reshape(-1), n_points - 1).reshape(n_slots, -1)
    first = x_.clip(x_.floor(lo), 0.0, None) + 0.5
    last = x_.where(drawn, x_.minimum(x_.floor(hi), width + (height - width) * rows - 1), -1.0) + 0.5
    offset = -0.5 * stride_major  # [px] in its picture = centre * stride_major + j * stride_minor + offset
    chord_base = x_.repeat(base, n_points - 1)  # [V * K]
    spare = flat.shape[0] - 1
    # the pixel of each path's end, its tip: [C, V]
    ti, tj = x_.floor(row[..., -1]), x_.floor(col[..., -1])
    inside = (ti >= 0) & (ti < height) & (tj >= 0) & (tj < width) & ok
    tips = x_.where(inside, x_.i64(ti * width + tj) + base, spare)
    # the steps [S, n, V * K] of runs of slots that take as many (fresh large arrays cost page
    # faults, many small ones a call each): all slots at once while that is small
    if steps is None:  # as many as each slot's longest chord needs
        widths = [int(w) + 1 for w in x_.amax(last - first, 1).tolist()]
        if n_slots * max(widths) * first.shape[1] <= SMALL:
            widths = [max(widths)] * n_slots
    else:
        widths = [steps] * n_slots
    start = 0
    while start < n_slots:
        end = start + 1
        while end < n_slots and widths[end] == widths[start]:
            end += 1
        n, group = widths[start], slice(start, end)
        if n > 0:
            centre = first[group, None] + index_i[:n, None]
            t = x_.minimum(x_.maximum(centre, lo[group, None]), hi[group, None])  # the nearest chord point
            j = x_.floor(b0[group, None] + (t - a0[group, None]) * slope[group, None])  # exact at the start
            draw = (centre <= last[group, None]) & (j >= 0) & (j < n_minor[group, None])
            local = centre * stride_major[group, None] + j * stride_minor[group, None] + offset[group, None]
            index = x_.where(draw, x_.i64(local) + chord_base, spare)
        for c in range(start, end):
            flat[tips[c]] = shade[c]
            if n > 0:
                flat[index[c - start]] = x_.repeat(shade[c], n_points - 1)  # [n, V * K] <- [V * K]
        start = end
