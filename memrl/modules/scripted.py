"""A rule-based stable driver: the prior-knowledge maker and an evaluation baseline.

It reads the world state (privileged) and drives with the same 9 actions as the agent:

* **lateral**: a cascaded controller on the lateral offset ``e`` from a reference lane centre
  (lateral speed wanted ``-k_y e``, limited; curvature wanted from the lateral-speed error),
  rounded each step to one curvature change of -1, 0 or +1 step. The inner loop is much
  faster than the outer one, so the car settles on the centre line without overshoot.
* **longitudinal**: the largest speed from which a gentle brake (``planning_decel``) still
  keeps ``front_gap`` + a time headway to the car ahead, and the smallest speed that keeps a
  faster car behind from closing below ``rear_gap``; between the two, the cruise speed.
* **lane change**: one lane at a time toward the target lane, started when the gaps to every
  car in the destination lane are safe for the relative speeds; otherwise the driver picks the
  nearest reachable gap in that lane and adjusts its speed to line up with it. Once started it
  keeps going with relaxed margins, and aborts only while its centre is still in its own lane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.render import BEVRenderer
from memrl.envs.vehicles import action_index
from memrl.modules.policy import DrivingPolicy


@dataclass
class _Scene:
    """Snapshot of the other cars relative to the agent (arrays over cars)."""

    front: np.ndarray
    """Longitudinal extents [m] of the other cars: front bumpers (max x of their corners)."""
    back: np.ndarray
    """Rear bumpers [m] (min x of their corners)."""
    left: np.ndarray
    """Smallest y of each car's body [m]."""
    right: np.ndarray
    """Largest y of each car's body [m]."""
    vx: np.ndarray
    """Speed along the road [m/s]."""
    ego_front: float
    ego_back: float
    ego_left: float
    ego_right: float
    ego_y: float
    ego_vy: float
    ego_v: float

    @classmethod
    def of(cls, env: LaneChangeEnv) -> _Scene:
        ego = env.vehicle
        corners = BEVRenderer.car_corners([ego, *env.others])  # [N + 1, 4, (x, y)]
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        vx = np.array([c.speed * np.cos(c.heading) for c in env.others])
        return cls(
            front=hi[1:, 0], back=lo[1:, 0], left=lo[1:, 1], right=hi[1:, 1], vx=vx,
            ego_front=float(hi[0, 0]), ego_back=float(lo[0, 0]),
            ego_left=float(lo[0, 1]), ego_right=float(hi[0, 1]),
            ego_y=float(ego.position[1]), ego_vy=float(ego.speed * np.sin(ego.heading)),
            ego_v=float(ego.speed * np.cos(ego.heading)),
        )

    def in_band(self, lo: float, hi: float, margin: float) -> np.ndarray:
        """Mask of the cars whose body overlaps the lateral band [lo, hi] widened by ``margin``."""
        return (self.right > lo - margin) & (self.left < hi + margin)


# Hand-written: highway-env's IDM/MOBIL drivers command continuous acceleration and steering
# toward lane centres, not the agent's 9 discrete speed/curvature changes.
class ScriptedDriver(DrivingPolicy):
    """Holds the lane centre, keeps safe gaps by speed, changes lane when the gap is safe.

    Args:
        cruise_speed: speed kept on a free road [m/s] (other cars drive at 5-9 m/s).
        min_speed: lowest speed it chooses unless a car ahead forces it lower [m/s].
        max_speed: highest speed it chooses [m/s].
        planning_decel: deceleration assumed when computing safe speeds [m/s^2]; the car can
            do 1 m/s^2 (0.1 m/s per 0.1 s step), the rest is margin.
        front_gap: bumper-to-bumper gap kept to the car ahead at equal speeds [m].
        rear_gap: gap kept to a faster car behind (which never brakes) [m].
        time_headway: extra gap per m/s of own speed to the car ahead [s].
        lateral_gain: lateral speed wanted per metre of offset from the lane centre [1/s].
        lateral_speed_gain: lateral acceleration wanted per m/s of lateral-speed error [1/s].
        max_lateral_speed: lateral speed limit during a lane change [m/s].
        max_heading: heading limit during a lane change [rad].
        align_gain: speed change wanted per metre to the chosen gap in the next lane [1/s].
        max_align_speed: largest speed difference to the gap used to line up with it [m/s].
        align_buffer: extra gap [m] beyond the merge test's, aimed at when lining up.
        align_horizon: how far ahead in time the driver looks for a gap it can reach [s].
        commit_margin: fraction of the safety gaps still required once a change has started.
        band_margin: lateral clearance under which a car counts as in the agent's way [m].
        speed_tolerance: speed error below which the speed is kept [m/s].
        merge_window: when > 0, a lane change also starts only once no car of the
            destination lane is within this distance [m] ahead of the agent's front or behind
            its rear bumper, and the driver lines up with gaps that leave it: a rule on
            positions, which the agent can see in its frames, unlike the relative speeds the
            kinematic test uses. 0: the kinematic test alone.
    """

    def __init__(
        self,
        *,
        cruise_speed: float = 8.0,
        min_speed: float = 1.0,
        max_speed: float = 14.0,
        planning_decel: float = 0.6,
        front_gap: float = 4.0,
        rear_gap: float = 3.0,
        time_headway: float = 0.5,
        lateral_gain: float = 0.6,
        lateral_speed_gain: float = 3.0,
        max_lateral_speed: float = 1.2,
        max_heading: float = 0.3,
        align_gain: float = 0.5,
        max_align_speed: float = 3.0,
        align_buffer: float = 2.0,
        align_horizon: float = 30.0,
        commit_margin: float = 0.5,
        band_margin: float = 0.3,
        speed_tolerance: float = 0.05,
        merge_window: float = 0.0,
    ) -> None:
        self.cruise_speed = cruise_speed
        self.min_speed = min_speed
        self.max_speed = max_speed
        self.planning_decel = planning_decel
        self.front_gap = front_gap
        self.rear_gap = rear_gap
        self.time_headway = time_headway
        self.lateral_gain = lateral_gain
        self.lateral_speed_gain = lateral_speed_gain
        self.max_lateral_speed = max_lateral_speed
        self.max_heading = max_heading
        self.align_gain = align_gain
        self.max_align_speed = max_align_speed
        self.align_buffer = align_buffer
        self.align_horizon = align_horizon
        self.commit_margin = commit_margin
        self.band_margin = band_margin
        self.speed_tolerance = speed_tolerance
        self.merge_window = merge_window
        self.home_lane = 0
        """Lane the car keeps (or leaves, while ``changing``)."""
        self.changing = False
        """Whether a change to the next lane toward the target is under way."""

    # ------------------------------------------------------------------------------ API
    def reset(self, env: LaneChangeEnv) -> None:
        self.home_lane = env.current_lane()
        self.changing = False

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        scene = _Scene.of(env)
        w = env.cfg.lane_width
        if self.changing and env.current_lane() != self.home_lane:
            self.home_lane, self.changing = env.current_lane(), False  # centre crossed over
        dest = None
        if self.home_lane != env.target_lane:
            dest = self.home_lane + int(np.sign(env.target_lane - self.home_lane))
        speed_ref = self.cruise_speed
        if dest is not None:
            safe = self._merge_safe(scene, dest, w, relaxed=self.changing)
            if safe:
                self.changing = True
            elif self.changing and abs(scene.ego_y - self.home_lane * w) < 0.5 * w:
                self.changing = False  # abort: still mostly in the own lane
            if not self.changing:
                speed_ref = self._align_speed(scene, dest, w)
        lane = dest if self.changing and dest is not None else self.home_lane
        band = self._corridor(scene, lane * w, 0.5 * env.cfg.vehicle_width)
        speed = self._safe_speed(scene, band, speed_ref)
        return action_index(self._speed_sign(env, speed), self._curvature_sign(env, lane * w))

    # ---------------------------------------------------------------------- lateral
    def _curvature_sign(self, env: LaneChangeEnv, y_ref: float) -> int:
        car = env.vehicle
        e = float(car.position[1]) - y_ref
        vy = car.speed * np.sin(car.heading)
        v = max(car.speed, 1.0)
        # Lateral speed limits: the configured one, a heading limit, and the speed from which
        # half the largest lateral acceleration (v^2 * curvature_limit) still stops at the centre.
        brake = 0.5 * v * v * env.cfg.curvature_limit
        limit = min(self.max_lateral_speed, v * np.sin(self.max_heading), np.sqrt(2.0 * brake * abs(e)))
        vy_ref = -float(np.sign(e)) * min(self.lateral_gain * abs(e), limit)
        # d(vy)/dt = v^2 * kappa * cos(heading)
        kappa_ref = self.lateral_speed_gain * (vy_ref - vy) / (v * v * max(np.cos(car.heading), 0.5))
        step = env.cfg.curvature_step
        return int(np.clip(np.round((kappa_ref - car.curvature) / step), -1, 1))

    # ------------------------------------------------------------------ longitudinal
    def _speed_sign(self, env: LaneChangeEnv, speed: float) -> int:
        error = speed - env.vehicle.speed
        return 0 if abs(error) <= self.speed_tolerance else int(np.sign(error))

    def _ahead_limit(self, gap: float, lead_speed: float) -> float:
        """Largest speed from which braking at ``planning_decel`` keeps the wanted front gap."""
        room = gap - self.front_gap - self.time_headway * lead_speed
        if room <= 0:
            return lead_speed + room  # too close already: drop below the leader's speed
        return lead_speed + float(np.sqrt(2.0 * self.planning_decel * room))

    def _behind_limit(self, gap: float, rear_speed: float) -> float:
        """Smallest speed that keeps a car behind (which never brakes) from closing in."""
        room = gap - self.rear_gap
        if room <= 0:
            return rear_speed - room
        return rear_speed - float(np.sqrt(2.0 * self.planning_decel * room))

    @staticmethod
    def _corridor(scene: _Scene, y_ref: float, half_width: float) -> tuple[float, float]:
        """Lateral band [m] the car occupies now or will sweep on its way to ``y_ref``."""
        return min(scene.ego_left, y_ref - half_width), max(scene.ego_right, y_ref + half_width)

    def _safe_speed(self, scene: _Scene, band: tuple[float, float], speed_ref: float) -> float:
        """Speed wanted: ``speed_ref`` bounded by the cars ahead and behind in ``band``."""
        upper, lower = self.max_speed, self.min_speed
        mask = scene.in_band(*band, self.band_margin)
        for i in np.flatnonzero(mask):
            if scene.back[i] >= scene.ego_front - 1e-6:  # ahead
                upper = min(upper, self._ahead_limit(scene.back[i] - scene.ego_front, scene.vx[i]))
            elif scene.front[i] <= scene.ego_back + 1e-6:  # behind
                lower = max(lower, self._behind_limit(scene.ego_back - scene.front[i], scene.vx[i]))
            else:  # alongside and overlapping the corridor: back off
                upper = min(upper, scene.vx[i] - 1.0)
        if lower > upper:  # squeezed: split the difference
            return 0.5 * (lower + upper)
        return float(np.clip(speed_ref, lower, upper))

    # ------------------------------------------------------------------- lane change
    def _merge_safe(self, scene: _Scene, lane: int, w: float, relaxed: bool) -> bool:
        """Whether every car in ``lane`` is far enough ahead or behind for the speeds involved."""
        scale = self.commit_margin if relaxed else 1.0
        v = scene.ego_v
        mask = scene.in_band(lane * w - 0.5 * w, lane * w + 0.5 * w, 0.0)
        window = scale * self.merge_window
        if window > 0 and bool(np.any(mask & (scene.back < scene.ego_front + window)
                                      & (scene.front > scene.ego_back - window))):
            return False
        for i in np.flatnonzero(mask):
            if scene.back[i] >= scene.ego_front:
                gap, closing = scene.back[i] - scene.ego_front, v - scene.vx[i]
                need = self.front_gap + self.time_headway * v
            elif scene.front[i] <= scene.ego_back:
                gap, closing = scene.ego_back - scene.front[i], scene.vx[i] - v
                need = self.rear_gap + self.time_headway * scene.vx[i]
            else:
                return False
            need += max(closing, 0.0) ** 2 / (2.0 * self.planning_decel)
            if gap < scale * need:
                return False
        return True

    def _slots(self, scene: _Scene, lane_cars: np.ndarray) -> list[tuple[float, float, float, float, float]]:
        """Gaps between consecutive cars of the destination lane.

        Each is ``(lo, hi, lo_speed, hi_speed, speed)``: the agent's rear bumper must lie in
        ``[lo, hi]`` for the merge test to pass at matched speeds (plus ``align_buffer``); the
        bounds move with the cars behind and ahead at ``lo_speed`` and ``hi_speed``; ``speed``
        is the speed to hold inside the gap.
        """
        order = lane_cars[np.argsort(scene.back[lane_cars])]
        length = scene.ego_front - scene.ego_back
        pairs = [(None, order[0]), *zip(order[:-1], order[1:], strict=True), (order[-1], None)]
        slots = []
        for rear, front in pairs:
            lo, hi, lo_speed, hi_speed, speed = -np.inf, np.inf, 0.0, 0.0, self.cruise_speed
            if rear is not None:
                lo_speed = float(scene.vx[rear])
                lo = (float(scene.front[rear]) + self.align_buffer
                      + max(self.rear_gap + self.time_headway * lo_speed, self.merge_window))
                speed = max(speed, lo_speed)
            if front is not None:
                hi_speed = float(scene.vx[front])
                hi = (float(scene.back[front]) - length - self.align_buffer
                      - max(self.front_gap + self.time_headway * scene.ego_v, self.merge_window))
                speed = min(speed, hi_speed)
            slots.append((lo, hi, lo_speed, hi_speed, speed))
        return slots

    def _blockers(self, scene: _Scene, lane_cars: np.ndarray) -> tuple[float, float, float, float]:
        """Bounds on the agent's rear bumper set by its own lane's cars, and their speeds."""
        own = np.flatnonzero(scene.in_band(scene.ego_left, scene.ego_right, 0.0))
        own = own[~np.isin(own, lane_cars)]
        length = scene.ego_front - scene.ego_back
        lo, lo_speed, hi, hi_speed = -np.inf, 0.0, np.inf, 0.0
        for i in own:
            if scene.back[i] >= scene.ego_front and scene.back[i] - self.front_gap - length < hi:
                hi, hi_speed = scene.back[i] - self.front_gap - length, scene.vx[i]
            elif scene.front[i] <= scene.ego_back and scene.front[i] + self.rear_gap > lo:
                lo, lo_speed = scene.front[i] + self.rear_gap, scene.vx[i]
        return lo, lo_speed, hi, hi_speed

    def _align_speed(self, scene: _Scene, lane: int, w: float) -> float:
        """Speed that lines the car up with the gap of ``lane`` it can reach first.

        All other cars keep their speeds (as constant-speed cars do), so each gap's bounds, and
        the bounds set by the own lane's cars ahead and behind, move linearly. The driver finds
        the earliest time at which a gap, narrowed by those bounds, holds a point it can reach
        by changing its speed by at most ``max_align_speed``, and aims at that point.
        """
        lane_cars = np.flatnonzero(scene.in_band(lane * w - 0.5 * w, lane * w + 0.5 * w, 0.0))
        if lane_cars.size == 0:
            return self.cruise_speed
        own_lo, own_lo_speed, own_hi, own_hi_speed = self._blockers(scene, lane_cars)
        t = np.arange(0.0, self.align_horizon + 1e-9, 0.5)
        x, v = scene.ego_back, scene.ego_v
        dv, accel = self.max_align_speed, 0.8  # [m/s], [m/s^2]: 80% of the car's 1 m/s^2
        reach = np.where(t > dv / accel, dv * t - dv * dv / (2 * accel), 0.5 * accel * t * t)
        best: tuple[float, float, float] | None = None  # (time, goal, speed in gap)
        for lo, hi, lo_speed, hi_speed, speed in self._slots(scene, lane_cars):
            lo_t = np.maximum(lo + lo_speed * t, own_lo + own_lo_speed * t)
            hi_t = np.minimum(hi + hi_speed * t, own_hi + own_hi_speed * t)
            a_lo = np.maximum(lo_t, x + v * t - reach)
            a_hi = np.minimum(hi_t, x + v * t + reach)
            ok = np.flatnonzero(a_lo <= a_hi)
            if ok.size and (best is None or t[ok[0]] < best[0]):
                k = ok[0]
                best = (float(t[k]), float(np.clip(x + v * t[k], a_lo[k], a_hi[k])), speed)
        if best is None:
            return self.cruise_speed
        when, goal, speed = best
        if when == 0.0:
            return speed
        return float(np.clip((goal - x) / when, v - dv, v + dv))
