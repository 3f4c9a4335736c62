"""Crash diagnostics: hand-made crashes of each kind, classified the same by both engines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from highway_env.utils import are_polygons_intersecting

from memrl.envs.batched import BatchedLaneChange
from memrl.envs.batched_physics import overlap
from memrl.envs.crash import CRASH_KINDS, NO_CRASH, classify, classify_batch, kind_name
from memrl.envs.render import body_corners
from memrl.envs.vehicles import IDLE
from tests.helpers import empty_road

W = 4.0  # lane width [m]; lanes 0 and 1, road edges at y = -2 and y = 6
L, B = 5.0, 2.0  # body [m]

# (kind, agent (x, y, heading, speed, curvature), other cars, closing speed after one 0.1 s step)
CASES = [
    # runs into a stopped car 0.5 m ahead at 6 m/s (0.6 m in the step)
    ("ahead", (500.0, W, 0.0, 6.0, 0.0), [(505.5, W, 0.0, 0.0, 0.0)], 6.0),
    # a car 0.5 m behind at 8 m/s, the agent at 2 m/s
    ("behind", (500.0, W, 0.0, 2.0, 0.0), [(494.5, W, 0.0, 8.0, 0.0)], 6.0),
    # a car in the next lane steers into the agent's side (0.05 m gap, 0.15 m sideways per step)
    ("side", (500.0, W, 0.0, 5.0, 0.0),
     [(499.0, W - 1.0 - 0.5 * (L * math.sin(0.3) + B * math.cos(0.3)) - 0.05, 0.3, 5.0, 0.0)],
     -5.0 * (1.0 - math.cos(0.3))),  # its centre is behind and slower along the road: opening
    # heading 0.1 rad off the road, 0.02 m from the low edge, 0.05 m sideways per step
    ("road_edge", (500.0, -2.0 + 0.5 * (L * math.sin(0.1) + B * math.cos(0.1)) + 0.02, -0.1, 5.0, 0.0), [],
     5.0 * math.sin(0.1)),
]


def _reference(agent, others):
    env = empty_road(vehicles_count=1)
    env.place_agent(agent[0], agent[1], agent[3], heading=agent[2], curvature=agent[4])
    for x, y, h, v, _ in others:
        env.add_car(x, y, v, heading=h)
    return env


def _engine(cases):
    engine = BatchedLaneChange({"target_lane": 1, "vehicles_count": 1}, len(cases))
    engine.reset(seeds=list(range(len(cases))))
    for i, (_, agent, others, _) in enumerate(cases):
        engine.state[i] = 0.0
        engine.present[i] = False
        engine.state[i, 0] = torch.tensor(agent, dtype=torch.float64)
        engine.present[i, 0] = True
        for k, row in enumerate(others):
            engine.state[i, 1 + k] = torch.tensor(row, dtype=torch.float64)
            engine.present[i, 1 + k] = True
    return engine


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_each_kind_is_classified_with_its_closing_speed_in_the_reference_env(case):
    kind, agent, others, closing = case
    assert classify(np.array(agent), np.array(others).reshape(-1, 5), W, 2, L, B)[0] == NO_CRASH  # apart
    env = _reference(agent, others)
    _, _, terminated, _, info = env.step(IDLE)
    assert terminated and bool(info["collided"])
    assert kind_name(int(info["crash_kind"])) == kind
    assert float(info["closing_speed"]) == pytest.approx(closing, abs=1e-9)


def test_the_batched_engine_classifies_the_same_crashes_the_same():
    engine = _engine(CASES)
    out = engine.step(torch.full((len(CASES),), IDLE))
    assert out.collided.tolist() == [True] * len(CASES)
    for i, (kind, agent, others, _) in enumerate(CASES):
        _, _, _, _, info = _reference(agent, others).step(IDLE)
        assert int(out.crash_kind[i]) == int(info["crash_kind"]) == CRASH_KINDS.index(kind) + 1
        assert float(out.closing_speed[i]) == float(info["closing_speed"])
    assert engine.info()["crash_kind"].tolist() == out.crash_kind.tolist()
    engine.reset([0])  # a new episode forgets the crash
    assert int(engine.crash_kind[0]) == NO_CRASH and float(engine.closing_speed[0]) == 0.0


def test_no_crash_has_no_kind_and_a_zero_closing_speed():
    env = _reference((500.0, W, 0.0, 5.0, 0.0), [(520.0, W, 0.0, 5.0, 0.0)])
    _, _, terminated, _, info = env.step(IDLE)
    assert not terminated and int(info["crash_kind"]) == NO_CRASH and info["closing_speed"] == 0.0
    engine = _engine([("", (500.0, W, 0.0, 5.0, 0.0), [(520.0, W, 0.0, 5.0, 0.0)], 0.0)])
    out = engine.step(torch.tensor([IDLE]))
    assert int(out.crash_kind[0]) == NO_CRASH and float(out.closing_speed[0]) == 0.0


def test_a_deep_rear_end_stays_ahead_and_the_nearest_of_two_cars_is_the_contact():
    # 2 m into the car ahead, 0.3 m to the side: front-to-back, not side
    assert classify(np.array([500.0, W, 0, 9.0, 0]), np.array([[503.0, W + 0.3, 0, 1.0, 0]]), W, 2, L, B) \
        == (CRASH_KINDS.index("ahead") + 1, 8.0)
    # touching a car beside (centre 0.5 m ahead, 1.9 m aside) and one 4.9 m behind: the side one is nearer
    kind, _ = classify(np.array([500.0, W, 0, 5.0, 0]),
                       np.array([[495.1, W, 0, 5.0, 0], [500.5, W - 1.9, 0, 5.0, 0]]), W, 2, L, B)
    assert kind_name(kind) == "side"


def _polygon(row):
    corners = body_corners(np.float64(row[0]), np.float64(row[1]), np.float64(row[2]), L, B)
    return np.vstack([corners, corners[:1]])  # closed, as highway-env's polygon()


def _classify_one_by_one(agent, others):
    """The classifier written car by car on highway-env's own polygon test (its definition)."""
    zero, best = np.zeros(2), None
    for row in others:
        if not are_polygons_intersecting(_polygon(agent), _polygon(row), zero, zero)[0]:
            continue
        dx, dy = row[0] - agent[0], row[1] - agent[1]
        sx, sy = abs(dx) / L, abs(dy) / B
        kind = ("ahead" if dx >= 0 else "behind") if sx >= sy else "side"
        closing = float(np.sign(dx) * (agent[3] * np.cos(agent[2]) - row[3] * np.cos(row[2])))
        if best is None or max(sx, sy) < best[0]:
            best = (max(sx, sy), CRASH_KINDS.index(kind) + 1, closing)
    if best is not None:
        return best[1], best[2]
    y, vy = _polygon(agent)[:4, 1], float(agent[3] * np.sin(agent[2]))
    if y.min() < -0.5 * W:
        return CRASH_KINDS.index("road_edge") + 1, -vy
    if y.max() > 1.5 * W:
        return CRASH_KINDS.index("road_edge") + 1, vy
    return NO_CRASH, 0.0


def test_the_batched_overlap_test_is_highway_envs_polygon_test():
    """Pairs of bodies apart, touching and overlapping at any heading: the same decision as
    highway-env's ``are_polygons_intersecting`` (at zero velocity), pair by pair."""
    rng = np.random.default_rng(0)
    n = 3000
    a = np.stack([rng.uniform(495, 505, n), rng.uniform(-1, 5, n), rng.uniform(-np.pi, np.pi, n)], -1)
    b = a + np.stack([rng.uniform(-6, 6, n), rng.uniform(-3, 3, n), rng.uniform(-np.pi, np.pi, n)], -1)
    a[:100, 2] = 0.0  # along the road: end to end and side by side, touching exactly
    b[:100] = a[:100] + np.where(np.arange(100)[:, None] < 50, [L, 0.0, 0.0], [0.0, B, 0.0])
    # At a heading, exact touching rests on sin/cos's last bit, which differs between numpy's SIMD
    # paths on different CPUs: end to end 5 nm into each other (overlap) or 5 nm apart (no overlap),
    # a margin of some 10^4 ulps of the coordinates (about 500 m).
    h, d = a[100:400, 2:3], L * (1 + np.where(np.arange(300)[:, None] < 150, -1e-9, 1e-9))
    b[100:400] = a[100:400] + np.concatenate([d * np.cos(h), d * np.sin(h), 0 * h], -1)
    rows = lambda c: np.concatenate([c, np.zeros((n, 2))], -1)  # noqa: E731
    got = overlap(rows(a), rows(b), L, B)
    zero = np.zeros(2)
    want = [are_polygons_intersecting(_polygon(p), _polygon(q), zero, zero)[0]
            for p, q in zip(a, b, strict=True)]
    assert got.tolist() == want
    assert all(want[100:250]) and not any(want[250:400])  # 5 nm into each other or apart
    assert 500 < sum(want) < n - 500
    assert overlap(torch.from_numpy(rows(a)), torch.from_numpy(rows(b)), L, B).tolist() == want


def test_the_batched_classifier_is_the_car_by_car_one():
    """Agents among 0-5 cars, some absent, near and touching at any heading and across the road
    edges: the same kinds and closing speeds (exactly) as the car-by-car classifier."""
    rng = np.random.default_rng(1)
    m, k = 2000, 5
    agent = np.stack([np.full(m, 500.0), rng.uniform(-2.5, 6.5, m), rng.normal(0, 0.4, m),
                      rng.uniform(0, 15, m), np.zeros(m)], -1)
    others = np.stack([500 + rng.uniform(-7, 7, (m, k)), rng.uniform(-2, 6, (m, k)),
                       rng.normal(0, 0.3, (m, k)), rng.uniform(0, 15, (m, k)), np.zeros((m, k))], -1)
    present = rng.random((m, k)) < 0.6
    kind, closing = classify_batch(agent, others, present, W, 2, L, B)
    want = [_classify_one_by_one(agent[i], others[i][present[i]]) for i in range(m)]
    assert list(zip(kind.tolist(), closing.tolist(), strict=True)) == want
    assert {int(c) for c in kind} == {NO_CRASH, *range(1, len(CRASH_KINDS) + 1)}
    assert classify(agent[0], others[0][present[0]], W, 2, L, B) == want[0]
    touch = overlap(np.broadcast_to(agent[:, None], others.shape), others, L, B)  # as the engine tests it
    given = classify_batch(agent, others, present, W, 2, L, B, touch=touch)
    assert list(zip(given[0].tolist(), given[1].tolist(), strict=True)) == want
    none = classify_batch(agent, np.zeros((m, 0, 5)), np.zeros((m, 0), dtype=bool), W, 2, L, B)
    assert list(zip(none[0].tolist(), none[1].tolist(), strict=True)) == [
        _classify_one_by_one(a, []) for a in agent]


def _crashed(records, kinds):
    """Give the collided ``records`` the crash kinds, closing speeds and car counts of ``kinds``."""
    crashed = [r for r in records if r.collided]
    for r, (kind, speed, cars) in zip(crashed, kinds, strict=True):
        r.crash_kind, r.closing_speed, r.vehicles = kind, speed, cars
    return records


def test_eval_json_and_the_report_table_count_crashes_by_kind_speed_and_cars(tmp_path):
    import json

    from memrl.evaluation.crashes import crash_section
    from memrl.evaluation.protocol import ProtocolConfig, scenario_seeds
    from memrl.evaluation.results import read_result, write_result
    from memrl.evaluation.stats import StatsConfig
    from tests.eval_helpers import records

    recs = records([True, False, False, False, True, False], [True, False, True, True, True, True],
                   lane="non_goal")
    kinds = [("ahead", 2.0, 1), ("ahead", 4.0, 1), ("side", -0.5, 3), ("road_edge", 0.3, 0)]
    recs = _crashed(recs, kinds)
    protocol = ProtocolConfig(episodes=6, initial_lanes=("non_goal",))
    result = write_result(tmp_path / "e", "Default", recs, protocol, scenario_seeds(0, 6), {"unit": "seed 0"})
    assert result.records() == recs  # the CSV keeps kind and speed (None without a crash)
    doc = json.loads((tmp_path / "e" / "eval.json").read_text())["crashes"]["non_goal"]
    assert (doc["episodes"], doc["crashes"]) == (6, 4)
    assert doc["by_kind"]["ahead"] == {"count": 2, "before_target": 1, "mean_closing": 3.0,
                                       "median_closing": 3.0, "by_cars": {"1": 2}}
    assert doc["by_kind"]["behind"] == {"count": 0, "before_target": 0, "mean_closing": None,
                                        "median_closing": None, "by_cars": {}}
    assert doc["by_kind"]["side"]["by_cars"] == {"3": 1} and doc["by_kind"]["road_edge"]["count"] == 1
    lines = crash_section([[read_result(tmp_path / "e")]], StatsConfig())
    assert ("| row | kind | crashes | before target lane | closing mean / median | 0 cars | 1 car "
            "| 3 cars |") in lines
    assert "| Default (6) | ahead | 2 | 1 | 3.00 / 3.00 | 0 | 2 | 0 |" in lines
    assert "| Default (6) | road_edge | 1 | 0 | 0.30 / 0.30 | 1 | 0 | 0 |" in lines
    assert not any("| behind |" in line for line in lines)


def test_csvs_from_before_the_crash_columns_still_read(tmp_path):
    import csv

    from memrl.evaluation.protocol import record_from_row
    from tests.eval_helpers import records

    row = records([False], [False])[0].row()
    del row["crash_kind"], row["closing_speed"]
    with (tmp_path / "old.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, list(row))
        w.writeheader()
        w.writerow(row)
    with (tmp_path / "old.csv").open(newline="") as f:
        rec = record_from_row(next(csv.DictReader(f)))
    assert rec.collided and rec.crash_kind == "" and rec.closing_speed is None


def test_crash_strips_show_the_last_frames_of_the_first_crashes_of_a_kind(tmp_path):
    from memrl.evaluation.crash_strips import crash_records, crash_strip
    from memrl.evaluation.protocol import ProtocolConfig, scenario_seeds
    from memrl.evaluation.results import write_result
    from memrl.evaluation.rollouts import Capture
    from tests.eval_helpers import records

    recs = records([False, True, False, False], [False] * 4, lane="random") + \
        records([False, False], [False] * 2, lane="non_goal")
    recs = _crashed(recs, [("side", 0.1, 2), ("ahead", 3.0, 1), ("side", 0.2, 4), ("side", 0.3, 5),
                           ("road_edge", 0.5, 0)])
    result = write_result(tmp_path / "e", "A", recs, ProtocolConfig(episodes=4), scenario_seeds(0, 4),
                          {"unit": "seed 0"})
    picked = crash_records(result, "side", 2)  # non-goal starts first, then by episode
    assert [(r.initial_lane, r.episode) for r in picked] == [("non_goal", 0), ("random", 0)]
    assert crash_records(result, "behind", 2) == []
    scene = np.zeros((40, 60, 3), np.uint8)
    caps = [Capture(r, [scene] * 12) for r in picked]
    img = crash_strip(caps, 8, "title")
    gap = 6
    assert img.shape[1] == 8 * 60 + 7 * gap and img.dtype == np.uint8
    short = crash_strip([Capture(picked[0], [scene] * 3)], 8, "t")  # an episode shorter than 8 steps
    assert short.shape[1] >= 3 * 60 + 2 * gap
