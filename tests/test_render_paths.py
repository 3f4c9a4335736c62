"""Every car's path (``bev.path_time``) as chords of its arc, each a 1-px line
(memrl.envs.render_paths): the chords' geometry, the pixels of a line against a hand
computation, curved paths against their true arcs, the fixed windows of accelerators, and
the column runs of paths along the road against a hand computation and against their chords."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import distance_transform_cdt, label

import memrl.envs.render as render
from memrl.envs.render import LABEL, BEVRenderer, View, arc_points
from memrl.envs.render_paths import chord_count, chord_points

VIEW = View(84, 84, 0.2, 0.8)


def test_chord_count_is_the_fewest_chords_within_the_tolerance_of_the_arc():
    # 30 m (15 m/s for 2 s) at 0.05 rad/m within 0.1 m (half a pixel across): 30 sqrt(0.05 / 0.8) = 7.5
    assert chord_count(30.0, 0.05, 0.1) == 8
    assert chord_count(30.0, 0.0, 0.1) == chord_count(0.0, 0.05, 0.1) == 1  # straight, or no path
    state = np.array([0.0, 0.0, 0.3, 0.05])
    arc = arc_points(state, np.linspace(0.0, 30.0, 3001))  # the arc, every centimetre
    for chords, within in ((8, True), (7, False)):
        xs, ys = chord_points(*state, 30.0, chords)
        a, b = np.stack([xs[:-1], ys[:-1]], -1), np.stack([xs[1:], ys[1:]], -1)  # [K, 2] chord ends
        # each arc point's distance to the nearest chord
        u = np.clip(((arc[:, None] - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0.0, 1.0)
        gap = np.linalg.norm(arc[:, None] - (a + u[..., None] * (b - a)), axis=-1).min(-1)
        assert (gap.max() <= 0.1) == within, (chords, gap.max())


def test_chord_points_lie_on_the_arc_on_numpy_and_torch():
    rng = np.random.default_rng(0)
    x, y, h = rng.uniform(400, 600, 50), rng.uniform(-2, 6, 50), rng.uniform(-1.5, 1.5, 50)
    k, length = rng.choice([0.0, 1e-12, 0.01, -0.05], 50), rng.uniform(0, 30, 50)
    for chords in (1, 3, 8):
        xs, ys = chord_points(x, y, h, k, length, chords)
        assert xs.shape == ys.shape == (chords + 1, 50)
        xs, ys = xs.T, ys.T
        for i in range(50):
            arc = arc_points(np.array([x[i], y[i], h[i], k[i]]), length[i] * np.arange(chords + 1) / chords)
            assert np.abs(np.stack([xs[i], ys[i]], -1) - arc).max() < 1e-9
        tx, ty = chord_points(*(torch.from_numpy(a) for a in (x, y, h, k, length)), chords)
        assert np.abs(tx.numpy().T - xs).max() < 1e-9 and np.abs(ty.numpy().T - ys).max() < 1e-9
    # straight along the road: every point on the car's line, exactly
    xs, ys = chord_points(*(np.array([v]) for v in (500.0, 4.0, 0.0, 0.0, 12.0)), 8)
    assert ys.T.tolist() == [[4.0] * 9] and xs[-1, 0] == 512.0


def _paths_only(renderer: BEVRenderer, center, paths, labels, lib=np):
    """The pictures of paths with their cars' bodies off the picture (path pixels only)."""
    cars = paths[..., :3].copy()
    cars[..., 0] += 1e4
    args = (center, np.full(len(center), -1), cars, labels, paths)
    out = renderer.render_batch(*(args if lib is np else (torch.from_numpy(a) for a in args)))
    return out if lib is np else out.numpy()


def test_a_slanted_path_steps_one_pixel_per_row_to_its_tip():
    """A straight path at heading atan(1/8) from the crop centre, 5 m/s for 2 s (one chord):
    in pixels it runs up from (row 42, col 42) to (42 - 10 cos / 0.8, 42 + 10 sin / 0.2) =
    (29.60, 48.20), 4 tan = 0.5 columns right per row up. Each row r from 42 up to the tip's
    row 29 holds the pixel of the line's point nearest the row's centre r + 0.5 (the tip's
    own in row 29): col = floor(42 + 0.5 (42 - t)), t = 42, 41.5, 40.5, ..., 30.5, 29.60."""
    renderer = BEVRenderer(VIEW, 2, 4.0, path_time=2.0, max_speed=15.0, channels=1)  # straight: 1 chord
    center = np.array([[500.0, 0.0]])
    paths = np.array([[[500.0, 0.0, math.atan(0.125), 0.0, 5.0]]])
    img = _paths_only(renderer, center, paths, np.array([[LABEL["constant"]]]))[0]
    plain = _paths_only(renderer, center, paths, np.array([[-1]]))[0]
    drawn = img != plain
    expected = {42: 42, 41: 42, 40: 42, 39: 43, 38: 43, 37: 44, 36: 44, 35: 45, 34: 45, 33: 46, 32: 46,
                31: 47, 30: 47, 29: 48}  # row: column (hand-computed above)
    assert sorted(zip(*np.nonzero(drawn), strict=True)) == sorted(expected.items())
    assert (img[drawn] == renderer.palette["constant"]).all()


def test_curved_paths_are_connected_lines_within_a_pixel_of_their_arcs():
    """Paths at any heading, curvature up to the limit and speed up to the highest, drawn as
    8 chords (the engines' default): one 8-connected line; the pixel the true arc ends in (the
    tip) drawn; every drawn pixel next to (or on) one the arc passes through, and every pixel the
    arc passes through next to a drawn one."""
    renderer = BEVRenderer(VIEW, 2, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    assert renderer._chords == 8
    rng = np.random.default_rng(3)
    v = 300
    center = np.stack([np.full(v, 500.0), rng.uniform(-1.0, 5.0, v)], -1)
    paths = np.stack([500.0 + rng.uniform(-20, 5, v), center[:, 1] + rng.uniform(-3, 3, v),
                      rng.normal(0, 0.3, v), rng.choice([0.0, 0.01, -0.02, 0.05, -0.05], v),
                      rng.uniform(0.5, 15, v)], -1)[:, None]
    labels = np.full((v, 1), LABEL["constant"])
    plain = _paths_only(renderer, center, paths, np.full((v, 1), -1))
    drawn = _paths_only(renderer, center, paths, labels) != plain
    checked = 0
    for i in range(v):
        s = np.linspace(0.0, 2.0 * paths[i, 0, 4], 20001)  # the arc, every millimetre or so
        col, row = renderer.to_pixels(center[i], arc_points(paths[i, 0, :4], s)).T
        if not ((col >= 0) & (col < 84) & (row >= 0) & (row < 84)).all():
            continue  # leaves the picture: only whole paths are checked
        checked += 1
        arc = np.zeros((84, 84), dtype=bool)
        arc[np.floor(row).astype(int), np.floor(col).astype(int)] = True
        assert label(drawn[i], structure=np.ones((3, 3)))[1] == 1
        assert drawn[i, int(np.floor(row[-1])), int(np.floor(col[-1]))]  # the tip
        assert distance_transform_cdt(~arc, metric="chessboard")[drawn[i]].max() <= 1
        assert distance_transform_cdt(~drawn[i], metric="chessboard")[arc].max() <= 1
        assert drawn[i].sum() <= arc.sum()  # no thicker than the arc's own pixels
    assert checked > 200


def test_fixed_windows_of_accelerators_draw_what_the_cpu_windows_draw(monkeypatch):
    """On an accelerator every chord takes the renderer's fixed number of steps (no host sync)
    and every path is drawn as chords; on the CPU as many as the longest chord needs, only the
    paths that can show, and those along the road as column runs: the same pixels, here at
    any heading (long chords across the road), along the road, and at the highest speed."""
    renderer = BEVRenderer(VIEW, 3, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    rng = np.random.default_rng(5)
    v, c = 64, 6
    center = np.stack([np.full(v, 500.0), rng.uniform(-1.0, 9.0, v)], -1)
    paths = np.stack([500.0 + rng.uniform(-40, 40, (v, c)), rng.uniform(-3, 11, (v, c)),
                      rng.uniform(-np.pi, np.pi, (v, c)), rng.uniform(-0.05, 0.05, (v, c)),
                      rng.choice([0.0, 7.0, 15.0], (v, c))], -1)
    paths[:, ::2, 2:4] = 0.0  # along the road
    labels = rng.integers(-1, 7, (v, c))
    dynamic = _paths_only(renderer, center, paths, labels, torch)
    paint = render.paint_paths
    windows = []

    def fixed(*args):
        windows.append(args[-2])
        return paint(*args[:-2], renderer._chord_steps, args[-1])

    monkeypatch.setattr(render, "paint_paths", fixed)
    assert np.array_equal(_paths_only(renderer, center, paths, labels, torch), dynamic)
    assert windows == [None]  # the CPU's windows were the ones replaced
    assert (dynamic != _paths_only(renderer, center, paths, labels * 0 - 1)).sum() > 1000


@pytest.mark.parametrize("speed", [0.0, 1e-9])
def test_a_standing_car_draws_its_tip_only(speed):
    renderer = BEVRenderer(VIEW, 2, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    center = np.array([[500.0, 0.0]])
    paths = np.array([[[510.1, 1.1, 0.2, 0.05, speed]]])  # row floor(42 - 12.625) = 29, col floor(47.5) = 47
    drawn = (_paths_only(renderer, center, paths, np.array([[LABEL["constant"]]]))
             != _paths_only(renderer, center, paths, np.array([[-1]])))[0]
    assert list(zip(*np.nonzero(drawn), strict=True)) == [(29, 47)]


def test_all_slots_at_once_and_runs_of_slots_draw_the_same(monkeypatch):
    """Few views take every slot's steps in one pass (padded to the longest), many views runs of
    slots with equal windows: the same pixels, later slots' paths over earlier ones either way."""
    import memrl.envs.render_paths as paths_module

    renderer = BEVRenderer(VIEW, 2, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    rng = np.random.default_rng(7)
    v, c = 40, 6
    center = np.stack([np.full(v, 500.0), rng.uniform(-1.0, 5.0, v)], -1)
    paths = np.stack([500.0 + rng.uniform(-30, 30, (v, c)), rng.choice([0.0, 4.0], (v, c)),
                      rng.normal(0, 0.4, (v, c)) * (rng.random((v, c)) < 0.5),
                      rng.uniform(-0.05, 0.05, (v, c)), rng.uniform(0, 15, (v, c))], -1)
    paths[:, 3:, :2] = paths[:, :3, :2] + [3.0, 0.0]  # paths crossing others: the draw order shows
    labels = rng.integers(-1, 7, (v, c))
    pictures = []
    for small in (1 << 30, 0):
        monkeypatch.setattr(paths_module, "SMALL", small)
        pictures.append(_paths_only(renderer, center, paths, labels))
    assert np.array_equal(*pictures)
    assert (pictures[0] != _paths_only(renderer, center, paths, np.full((v, c), -1))).sum() > 500


def _along(v, rng):
    """``v`` views, each with 6 cars straight along the road (heading and curvature 0) at any
    speed, near and far (partly and wholly off the picture), some absent, mixed shades."""
    center = np.stack([np.full(v, 500.0), rng.uniform(-1.0, 9.0, v)], -1)
    c = 6
    y = rng.choice([0.0, 4.0, 8.0], (v, c)) + rng.choice([0.0, 0.03, -1.7, 9.0], (v, c))
    paths = np.stack([500.0 + rng.uniform(-70, 50, (v, c)), y, np.zeros((v, c)), np.zeros((v, c)),
                      rng.choice([0.0, 5.0, 9.0, 15.0], (v, c))], -1)
    shades = [-1, LABEL["agent"], LABEL["constant"], LABEL["learned"]]
    labels = rng.choice(shades, (v, c), p=[0.1, 0.1, 0.6, 0.2])
    return center, paths, labels


def test_paths_along_the_road_are_the_column_runs_of_a_hand_computation(monkeypatch):
    """64 views (enough for column runs), one car each straight along the road: its column
    floor(42 + dy / 0.2), rows from its tip's floor(42 - (dx + 2 v) / 0.8) to its own
    floor(42 - dx / 0.8), clipped to the picture; nothing else drawn, and the runs write those
    pixels once each (no write to the spare element)."""
    import memrl.envs.render_paths as paths_module

    renderer = BEVRenderer(VIEW, 2, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    rng = np.random.default_rng(11)
    v = paths_module.MANY
    center = np.stack([np.full(v, 500.0), np.zeros(v)], -1)
    dx, dy = rng.uniform(-40.0, 40.0, v).round(1) + 0.05, rng.uniform(-9.0, 9.0, v).round(1) + 0.05
    speed = rng.choice([0.0, 3.0, 7.5, 15.0], v)
    paths = np.stack([500.0 + dx, dy, np.zeros(v), np.zeros(v), speed], -1)[:, None]
    written = []  # the offsets the column runs write: exactly their pixels, none to the spare
    runs = paths_module._column_runs
    monkeypatch.setattr(paths_module, "_column_runs", lambda *a: written.append(runs(*a)) or written[-1])
    drawn = (_paths_only(renderer, center, paths, np.full((v, 1), LABEL["constant"]))
             != _paths_only(renderer, center, paths, np.full((v, 1), -1)))
    for i in range(v):
        col = math.floor(42 + dy[i] / 0.2)
        top, bottom = math.floor(42 - (dx[i] + 2 * speed[i]) / 0.8), math.floor(42 - dx[i] / 0.8)
        rows = range(max(top, 0), min(bottom, 83) + 1)
        expected = {(r, col) for r in rows} if 0 <= col < 84 else set()
        assert set(zip(*np.nonzero(drawn[i]), strict=True)) == expected, i
    assert drawn.sum() > 500
    offsets = np.concatenate([index.reshape(-1) for index, *_ in written[0][0]])  # one layer, once
    assert len(written) == 1 and len(offsets) == len(np.unique(offsets)) == drawn.sum()


def test_column_runs_draw_what_the_chords_draw(monkeypatch):
    """Many views of cars along the road among curved and turned ones, the later slots' paths
    over the earlier ones: the column runs (with the paths that cannot show left out) give the
    chords' pixels exactly, on numpy and torch."""
    import memrl.envs.render_paths as paths_module

    renderer = BEVRenderer(VIEW, 3, 4.0, path_time=2.0, max_speed=15.0, max_curvature=0.05, channels=1)
    rng = np.random.default_rng(12)
    center, paths, labels = _along(300, rng)
    turned = rng.random(paths.shape[:2]) < 0.3
    paths[..., 2] = np.where(turned, rng.normal(0, 0.3, turned.shape), 0.0)
    paths[..., 3] = np.where(turned, rng.choice([0.0, 0.02, -0.05], turned.shape), 0.0)
    paths[:, 3:, :2] = paths[:, :3, :2] + [3.0, 0.0]  # paths over others: the draw order shows
    pictures = {}
    for many in (paths_module.MANY, 10 ** 9):  # column runs, then chords only
        monkeypatch.setattr(paths_module, "MANY", many)
        for lib in (np, torch):
            pictures[many, lib] = _paths_only(renderer, center, paths, labels, lib)
    first = next(iter(pictures.values()))
    assert all(np.array_equal(first, p) for p in pictures.values())
    assert (first != _paths_only(renderer, center, paths, np.full(labels.shape, -1))).sum() > 3000
