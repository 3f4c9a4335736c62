"""The OpenCV bird's-eye view: geometry of the crop, shades, grayscale, any-car centring."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs.transforms.functional import rgb_to_grayscale

from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.render import PALETTE, gray_palette
from tests.helpers import empty_road

LAT, LON = 0.2, 0.8  # default m/px across / along the road


def centroid(mask: np.ndarray) -> tuple[float, float]:
    """(col, row) of the mask's pixel centres, in continuous pixel coordinates."""
    rows, cols = np.nonzero(mask)
    return cols.mean() + 0.5, rows.mean() + 0.5


def test_gray_levels_stay_distinct():
    levels = sorted(gray_palette(PALETTE).values())
    assert min(np.diff(levels)) >= 25, levels


def test_agent_at_crop_centre_with_its_size():
    env = empty_road()
    env.place_agent(500.0, 4.0, speed=5.0)
    img = env.observe_from(env.vehicle, env.target_lane)[0]
    agent = img == gray_palette(PALETTE)["agent"]
    col, row = centroid(agent)
    assert col == pytest.approx(42.0, abs=0.5) and row == pytest.approx(42.0, abs=0.5)
    rows, cols = np.nonzero(agent)
    assert cols.max() - cols.min() + 1 == round(2.0 / LAT)   # 2 m wide -> 10 px
    assert rows.max() - rows.min() + 1 == 6  # 5 m long -> 6.25 px


@pytest.mark.parametrize(("dx", "dy"), [(10.0, 4.0), (-20.0, -4.0), (25.0, 0.0), (-8.0, 3.0)])
def test_other_car_lands_where_its_offset_predicts(dx, dy):
    env = empty_road()
    env.place_agent(500.0, 2.0, speed=5.0)  # on the lane line, so +-4 m stays on the road
    env.add_car(500.0 + dx, 2.0 + dy, speed=5.0)
    img = env.observe_from(env.vehicle, env.target_lane)[0]
    other = img == gray_palette(PALETTE)["constant"]
    col, row = centroid(other)
    assert col == pytest.approx(42.0 + dy / LAT, abs=0.5)
    assert row == pytest.approx(42.0 - dx / LON, abs=0.5)


def test_crop_centred_on_another_car_shows_the_agent_as_learned():
    env = empty_road()
    env.place_agent(500.0, 0.0, speed=5.0)
    other = env.add_car(510.0, 4.0, speed=5.0)
    img = env.observe_from(other, target_lane=0)[0]
    g = gray_palette(PALETTE)
    col, row = centroid(img == g["agent"])
    assert (col, row) == (pytest.approx(42.0, abs=0.5), pytest.approx(42.0, abs=0.5))
    col, row = centroid(img == g["learned"])
    assert col == pytest.approx(42.0 - 4.0 / LAT, abs=0.5)
    assert row == pytest.approx(42.0 + 10.0 / LON, abs=0.5)
    # the target-lane shade now marks lane 0, left of this car
    assert img[5, 42 - 20] == g["target_lane"] and img[5, 42] == g["road"]


def test_gray_drawing_equals_torchrl_grayscale_of_rgb_drawing():
    gray_env = LaneChangeEnv(config={"bev": {"grayscale": True}})
    rgb_env = LaneChangeEnv(config={"bev": {"grayscale": False}})
    for seed in range(3):
        g, _ = gray_env.reset(seed=seed)
        c, _ = rgb_env.reset(seed=seed)
        for action in [0, 2, 6, 8, 4]:
            g = gray_env.step(action)[0]
            c = rgb_env.step(action)[0]
        assert c.shape == (3, 84, 84) and g.shape == (1, 84, 84)
        expected = rgb_to_grayscale(torch.from_numpy(c)).numpy()
        assert np.array_equal(g, expected)


def test_road_edges_lane_line_and_target_shade_columns():
    env = empty_road()
    env.place_agent(500.0, 0.0, speed=5.0)  # lane 0 centre at column 42
    img = env.observe_from(env.vehicle, env.target_lane)[0]
    g = gray_palette(PALETTE)
    # left edge at y=-2 m -> col 32; right edge at y=6 m -> col 72; lane line at y=2 m -> 52
    assert img[10, 31] == g["offroad"] and img[10, 32] == g["marking"]
    assert img[10, 71] == g["marking"] and img[10, 72] == g["offroad"]
    assert img[10, 40] == g["road"] and img[10, 60] == g["target_lane"]
    line = img[:, 51] == g["marking"]  # 1 px band [51.5, 52.5): the pixel centred at 51.5
    assert 0.3 < line.mean() < 0.7  # dashed: about half the rows


def test_dashes_move_with_the_car_and_repeat_every_period():
    env = empty_road()
    # x chosen so that no dash end falls on a pixel boundary (no rounding ties)
    env.place_agent(499.9, 0.0, speed=5.0)
    a = env.observe_from(env.vehicle, 1)[0, :, 51].copy()
    env.place_agent(501.5, 0.0, speed=5.0)  # 1.6 m = 2 px further
    b = env.observe_from(env.vehicle, 1)[0, :, 51].copy()
    env.place_agent(505.9, 0.0, speed=5.0)  # one dash period (6 m) further
    c = env.observe_from(env.vehicle, 1)[0, :, 51].copy()
    assert not np.array_equal(a, b)
    assert np.array_equal(np.roll(a, 2)[5:-5], b[5:-5])
    assert np.array_equal(a[2:-2], c[2:-2])


def test_scene_picture_is_rgb_and_not_blank():
    env = LaneChangeEnv(render_mode="rgb_array")
    env.reset(seed=0)
    pic = env.render()
    assert pic.shape == (500, 120, 3) and pic.dtype == np.uint8
    assert (pic == np.array(PALETTE["agent"], dtype=np.uint8)).all(-1).sum() > 100


@pytest.mark.parametrize("curvature", [0.0, 0.02, -0.02])
def test_path_cue_draws_the_arc_the_car_will_drive(curvature):
    agent_gray = gray_palette(PALETTE)["agent"]
    off = empty_road()
    off.place_agent(500.0, 2.0, speed=5.0, curvature=curvature)
    body = int((off.observe_from(off.vehicle, 1)[0] == agent_gray).sum())
    env = empty_road(bev={"path_length": 20.0})
    env.place_agent(500.0, 2.0, speed=5.0, curvature=curvature)
    img = env.observe_from(env.vehicle, 1)[0]
    agent = img == agent_gray
    assert agent.sum() > body + 15  # the body, plus ~20 px of line ahead of it
    # The arc's end, 20 m ahead: 25 rows above the centre; k s^2 / 2 = +-4 m = +-20 px across.
    end = env.bev.to_pixels(env.vehicle.position, env.bev.path_points(env.vehicle)[-1:])[0]
    assert end[1] == pytest.approx(42.0 - 20.0 * np.cos(0) / LON, abs=1.0)
    expected_col = 42.0 + (curvature * 20.0**2 / 2) / LAT
    assert end[0] == pytest.approx(expected_col, abs=1.0)
    top_rows = np.nonzero(agent[15:20])[1]
    assert top_rows.size and abs(top_rows.mean() + 0.5 - expected_col) <= 2.0
    assert (img[:15] != agent_gray).all()  # nothing beyond the path's end


def test_path_cue_is_off_by_default_and_checked():
    from memrl.envs.config import EnvConfigError

    assert LaneChangeEnv().bev.path_length == 0.0
    with pytest.raises(EnvConfigError, match="bev.path_length"):
        LaneChangeEnv(config={"bev": {"path_length": -1.0}})


def test_every_cars_path_shows_its_speed_as_the_lines_length():
    """``bev.path_time=2``: a car 20.4 m ahead in lane 1 (y 4.1) at 6 m/s and the agent at
    5 m/s, both straight: each draws a 1-px line from its centre row to where it will be in
    2 s, under the cars, in its own shade; nothing else in the picture changes."""
    gray = gray_palette(PALETTE)
    pictures = {}
    for path_time in (0.0, 2.0):
        env = empty_road(bev={"path_time": path_time})
        env.place_agent(500.0, 0.1, speed=5.0)
        env.add_car(520.4, 4.1, 6.0)
        pictures[path_time] = env.observe_from(env.vehicle, 1)[0]
    plain, img = pictures[0.0], pictures[2.0]
    # rows: floor(42 - dx / 0.8), columns: floor(42 + dy / 0.2) (crop centred on the agent)
    # other car: column floor(42 + 4.1 / 0.2) = floor(62.5) = 62; its centre row
    # floor(42 - 20.4 / 0.8) = floor(16.5) = 16, its tip 12 m further at floor(1.5) = 1;
    # its body covers rows 13..19 (centres within 5 m / 2 / 0.8 px = 3.125 px of 16.5)
    # agent: column floor(42 + 0.1 / 0.2) = 42; centre row 42, tip 10 m ahead at
    # floor(42 - 12.5) = 29; its body covers rows 39..44 (centres within 3.125 px of 42)
    expected = plain.copy()
    for row in range(1, 17):
        if not 13 <= row <= 19:
            expected[row, 62] = gray["constant"]
    for row in range(29, 43):
        if not 39 <= row <= 44:
            expected[row, 42] = gray["agent"]
    assert np.array_equal(img, expected)
    assert plain[1:13, 62].tolist() != [gray["constant"]] * 12  # (the line is new)


def test_absent_cars_draw_no_path_and_path_time_off_draws_none():
    from memrl.envs.render import LABEL, BEVRenderer, View

    view = View(84, 84, LAT, LON)
    on = BEVRenderer(view, 2, 4.0, path_time=2.0, max_speed=15.0, channels=1)
    off = BEVRenderer(view, 2, 4.0, channels=1)
    center, target = np.array([[500.0, 0.0]]), np.array([1])
    cars = np.array([[[500.0, 0.0, 0.0], [515.0, 4.0, 0.0]]])
    paths = np.array([[[500.0, 0.0, 0.0, 0.0, 5.0], [515.0, 4.0, 0.0, 0.02, 8.0]]])
    both = np.array([[LABEL["agent"], LABEL["constant"]]])
    only_agent = np.array([[LABEL["agent"], -1]])
    alone = on.render_batch(center, target, cars[:, :1], only_agent[:, :1], paths[:, :1])
    assert np.array_equal(on.render_batch(center, target, cars, only_agent, paths), alone)
    assert not np.array_equal(on.render_batch(center, target, cars, both, paths), alone)
    # path_time 0: the paths are not drawn, whatever is passed
    assert np.array_equal(off.render_batch(center, target, cars, both, None),
                          off.render_batch(center, target, cars, both, paths[..., 0, :4]))


def test_path_time_is_checked_and_not_combined_with_path_length():
    from memrl.envs.config import EnvConfigError

    assert LaneChangeEnv().bev.path_time == 0.0
    for bad in (-0.5, 10.5):
        with pytest.raises(EnvConfigError, match=r"bev\.path_time"):
            LaneChangeEnv(config={"bev": {"path_time": bad}})
    with pytest.raises(EnvConfigError, match=r"bev\.path_length,bev\.path_time': two path cues"):
        LaneChangeEnv(config={"bev": {"path_length": 20.0, "path_time": 2.0}})
