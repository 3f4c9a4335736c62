"""A discrete PID controller with output limits and anti-windup by conditional integration."""

from __future__ import annotations

from memrl.control.config import PIDConfig


class PID:
    """``u = P e + I integral(e) - D d(measurement)/dt``, clamped to ``output_limits``.

    Hand-written: no library in the stack has one (the ``simple-pid`` package would be a new
    dependency for 40 lines). The derivative acts on the measurement, so a step of the set
    point does not kick the output. Anti-windup by conditional integration (clamping): while the
    unclamped output lies beyond a limit and the error pushes it further out, the integral is
    frozen, so it never accumulates what the actuator cannot deliver and the loop recovers from
    saturation without the long overshoot of a wound-up integrator. The integral term itself is
    also kept within the output limits.

    Args:
        p: proportional gain [output / error].
        i: integral gain [output / (error x s)].
        d: derivative gain [output / (error / s)].
        output_limits: (low, high) clamp of the output.
        anti_windup: conditional integration on (True) or a plain, windup-prone integral (False).
    """

    def __init__(self, p: float, i: float = 0.0, d: float = 0.0,
                 output_limits: tuple[float, float] | list[float] = (-float("inf"), float("inf")),
                 anti_windup: bool = True) -> None:
        self.p, self.i, self.d = float(p), float(i), float(d)
        self.low, self.high = (float(v) for v in output_limits)
        if not self.low < self.high:
            raise ValueError(f"output_limits: need low < high, got {output_limits}")
        self.anti_windup = anti_windup
        self.integral = 0.0
        """Integral term [output units] (gain already applied, so a gain change is bumpless)."""
        self._last_measurement: float | None = None
        self.output = 0.0
        """Last (clamped) output."""
        self.saturated = False
        """Whether the last output was clamped."""

    @classmethod
    def from_config(cls, cfg: PIDConfig) -> PID:
        """Build from a :class:`~memrl.control.config.PIDConfig`."""
        return cls(cfg.p, cfg.i, cfg.d, tuple(cfg.output_limits), cfg.anti_windup)  # type: ignore[arg-type]

    def reset(self, integral: float = 0.0) -> None:
        """Forget the past; start the integral term at ``integral`` [output units]."""
        self.integral = float(integral)
        self._last_measurement = None
        self.output = 0.0
        self.saturated = False

    def update(self, setpoint: float, measurement: float, dt: float) -> float:
        """One control period of ``dt`` seconds; returns the clamped output."""
        error = setpoint - measurement
        derivative = 0.0
        if self.d and self._last_measurement is not None and dt > 0:
            derivative = -self.d * (measurement - self._last_measurement) / dt
        self._last_measurement = measurement
        step = self.i * error * dt
        unclamped = self.p * error + self.integral + step + derivative
        pushing_out = (unclamped > self.high and step > 0) or (unclamped < self.low and step < 0)
        if not (self.anti_windup and pushing_out):
            self.integral += step
            if self.anti_windup:
                self.integral = min(max(self.integral, self.low), self.high)
        raw = self.p * error + self.integral + derivative
        self.output = min(max(raw, self.low), self.high)
        self.saturated = self.output != raw
        return self.output
