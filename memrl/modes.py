"""Training modes as declared units: a mode is its list of stages, and nothing else names it.

Each mode (:class:`ModeSpec`) is declared once, here (Default, A, B) or from any module with
:func:`register_mode` (a test adds a toy mode from its own file): its config name and Table III
label, the ``mode`` keys it reads, its range checks and its stages in order. Each stage
(:class:`StageSpec`) gives its buffer recipe (the share the prior knowledge holds), its
exploration, its loss terms (:mod:`memrl.dqn.losses`), its optimizer settings and its stop
rule: an online stage runs until the run's budget; an offline stage (prior knowledge only,
no env steps) until its checks stop it (:mod:`memrl.dqn.stage1`, settings in
``mode.<settings>``), then the next stage starts from its weights.

The trainer, the checkpoints, the records, the reports and the study ask this registry; none of
them branches on a mode or stage name. Importing this module does not import torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from memrl.errors import config_error

Cfg = Any
"""The composed ``train`` config (a DictConfig)."""


@dataclass(frozen=True)
class StageSpec:
    """One stage of a mode."""

    name: str
    """Its tag in checkpoints, ``episodes.csv`` and ``updates.csv`` (unique over all modes)."""
    demo_share: Callable[[Cfg], float] = lambda cfg: 0.0
    """Share of the buffer (and of each stratified batch) the prior knowledge holds: 0 the
    agent's data only; 1 prior knowledge only, which makes the stage offline."""
    terms: Callable[[Cfg], tuple[Any, ...]] = lambda cfg: ()
    """Loss terms besides eq. (1)'s TD term, which every stage has (:mod:`memrl.dqn.losses`)."""
    exploration: Callable[[Cfg], tuple[float, float, int]] = \
        lambda cfg: (cfg.agent.eps_start, cfg.agent.eps_end, cfg.agent.eps_decay_frames)
    """Epsilon schedule (start, end, decay env steps) of an online stage."""
    lr: Callable[[Cfg], float | None] = lambda cfg: None
    """Its own Adam learning rate (None: the optimizer's, ``agent.lr`` at first)."""
    fresh_optimizer: bool = False
    """Starts a new Adam at ``agent.lr`` (the weights carry over; the target network is
    synced to them)."""
    settings: str | None = None
    """Offline stage: the ``mode`` key of its stop rule's settings (:class:`Stage1Config`)."""

    def offline(self, cfg: Cfg) -> bool:
        """Trains on prior knowledge alone (no env steps)."""
        return float(self.demo_share(cfg)) >= 1.0


@dataclass(frozen=True)
class ModeSpec:
    """A training mode: its stages and what it reads."""

    name: str
    """Its ``mode.name`` (``+mode=<name>``; ``default`` needs no ``+mode``)."""
    label: str
    """Its Table III row label."""
    stages: tuple[StageSpec, ...]
    reads: tuple[str, ...] = ("name",)
    """The ``mode`` keys it reads (dotted); the others cannot stop a resume or split a report
    row. ``example`` counts only where ``demos_path`` is null (the dataset is recorded from it)."""
    check: Callable[[Cfg], None] = lambda cfg: None
    """Range checks of its keys (raise :func:`memrl.errors.config_error` naming the key)."""
    overrides: tuple[str, ...] = field(default=())
    """Command-line overrides that select it (``+mode=A``); filled in by :func:`register_mode`."""

    @property
    def needs_demos(self) -> bool:
        """Reads prior knowledge: some stage keeps demos in its buffer (``demos_path`` read)."""
        return "demos_path" in self.reads

    @property
    def pretrains(self) -> bool:
        """Has an offline stage whose weights are saved (``checkpoints/stage1.pt``)."""
        return any(s.settings is not None for s in self.stages)

    def stage(self, name: str) -> StageSpec:
        """The stage called ``name`` (a checkpoint's ``counters.stage``)."""
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(f"mode {self.name} has no stage {name!r} (stages: {[s.name for s in self.stages]})")

    def next_stage(self, name: str) -> StageSpec | None:
        """The stage after ``name`` (None: the last)."""
        names = [s.name for s in self.stages]
        i = names.index(name)
        return self.stages[i + 1] if i + 1 < len(self.stages) else None

    def used(self, mode: dict[str, Any]) -> dict[str, Any]:
        """The values of ``mode`` this mode reads (a plain ``mode`` dict; unread keys dropped,
        ``example`` with its defaults filled in when it is read)."""
        from memrl.data.recipe import recipe_values

        out: dict[str, Any] = {}
        for key in self.reads:
            head, _, rest = key.partition(".")
            if head not in mode:
                continue
            if not rest:
                out[head] = mode[head]
            elif isinstance(mode[head], dict) and rest in mode[head]:
                out.setdefault(head, {})[rest] = mode[head][rest]
        if "example" in out:
            if out.get("demos_path") is None:
                out["example"] = recipe_values(out["example"])
            else:
                del out["example"]
        return out


MODES: dict[str, ModeSpec] = {}
"""Every declared mode by its ``mode.name``."""


def register_mode(spec: ModeSpec) -> ModeSpec:
    """Declare a mode (replacing one of the same name); its stage names must be new."""
    taken = {s.name for m in MODES.values() if m.name != spec.name for s in m.stages}
    clash = sorted(taken & {s.name for s in spec.stages})
    if clash:
        raise ValueError(f"mode {spec.name}: stage names {clash} are taken by another mode")
    overrides = () if spec.name == "default" else (f"+mode={spec.name}",)
    MODES[spec.name] = ModeSpec(spec.name, spec.label, spec.stages, spec.reads, spec.check, overrides)
    return MODES[spec.name]


def mode_of(cfg_or_name: Any) -> ModeSpec:
    """The mode of a train config (or of a ``mode.name``)."""
    name = cfg_or_name if isinstance(cfg_or_name, str) else str(cfg_or_name.mode.name)
    if name not in MODES:
        raise config_error("mode.name", f"unknown mode {name!r} (declared: {', '.join(MODES)})")
    return MODES[name]


def by_label(label: str) -> ModeSpec:
    """The mode whose Table III label is ``label``."""
    for spec in MODES.values():
        if spec.label == label:
            return spec
    raise KeyError(f"no mode labelled {label!r} (labels: {[m.label for m in MODES.values()]})")


def used(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (a plain train config) with only the ``mode`` keys its mode reads: a setting a
    run never used cannot stop it from resuming, nor split a report row."""
    mode = config.get("mode")
    if not isinstance(mode, dict) or mode.get("name") not in MODES:
        return config
    return {**config, "mode": MODES[str(mode["name"])].used(mode)}


# ------------------------------------------------------------------ Default, A and B (the paper)
def _margin(weight: float, margin: float) -> tuple[Any, ...]:
    from memrl.dqn.losses import margin_terms

    return tuple(margin_terms(float(weight), float(margin)))


def _need(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise config_error(key, message)


def _check_a(cfg: Cfg) -> None:
    m = cfg.mode
    _need(0 < m.demo_fraction < 1, "mode.demo_fraction", f"must be in (0, 1), got {m.demo_fraction}")
    _need(m.sampling in ("stratified", "proportional"), "mode.sampling",
          f"expected stratified or proportional, got {m.sampling!r}")
    _need(m.margin_weight >= 0, "mode.margin_weight", f"must be >= 0, got {m.margin_weight}")


def check_stage1(s1: Any) -> None:
    """The settings of an offline stage's stop rule (``mode.stage1``)."""
    _need(s1.criterion in ("agreement", "plateau", "agreement_or_plateau", "behaviour", "max_updates"),
          "mode.stage1.criterion", f"unknown criterion {s1.criterion!r}")
    _need(s1.drive_episodes >= 0, "mode.stage1.drive_episodes", "must be >= 0")
    _need(s1.criterion != "behaviour" or s1.drive_episodes >= 1, "mode.stage1.drive_episodes",
          "criterion 'behaviour' needs drive episodes (>= 1)")
    _need(0 < s1.drive_target <= 1, "mode.stage1.drive_target", "must be in (0, 1]")
    _need(0 < s1.holdout_fraction < 1, "mode.stage1.holdout_fraction", "must be in (0, 1)")
    _need(s1.max_updates >= 1 and s1.check_every >= 1, "mode.stage1.max_updates", "must be >= 1")
    _need(s1.lr is None or s1.lr > 0, "mode.stage1.lr", f"must be > 0 or null, got {s1.lr}")
    _need(s1.margin_weight >= 0, "mode.stage1.margin_weight", f"must be >= 0, got {s1.margin_weight}")


def _check_b(cfg: Cfg) -> None:
    m = cfg.mode
    _need(m.sampling in ("stratified", "proportional"), "mode.sampling",
          f"expected stratified or proportional, got {m.sampling!r}")
    check_stage1(m.stage1)
    s2 = m.stage2
    _need(0 <= s2.eps_end <= s2.eps_start <= 1, "mode.stage2.eps_start",
          "need 0 <= eps_end <= eps_start <= 1")
    _need(0 <= s2.demo_fraction < 1, "mode.stage2.demo_fraction",
          f"must be in [0, 1), got {s2.demo_fraction}")
    _need(s2.margin_weight >= 0, "mode.stage2.margin_weight", f"must be >= 0, got {s2.margin_weight}")


DEMOS = ("demos_path", "example")
"""The keys of a mode that reads prior knowledge."""

register_mode(ModeSpec("default", "Default", (StageSpec("default"),)))
"""Default: plain double DQN (eq. (1)), the agent's own data only."""

register_mode(ModeSpec(
    "A", "A",
    (StageSpec("A", demo_share=lambda cfg: cfg.mode.demo_fraction,
               terms=lambda cfg: _margin(cfg.mode.margin_weight, cfg.mode.stage1.margin)),),
    reads=("name", *DEMOS, "demo_fraction", "margin_weight", "sampling", "stage1.margin"),
    check=_check_a))
"""Mode A: prior knowledge permanently holds ``demo_fraction`` of the buffer, stratified
batches, DQfD's margin loss on their demos (weight ``margin_weight``, 0: the paper's A)."""

register_mode(ModeSpec(
    "B", "B",
    (StageSpec("B1", demo_share=lambda cfg: 1.0, settings="stage1",
               terms=lambda cfg: _margin(cfg.mode.stage1.margin_weight, cfg.mode.stage1.margin),
               lr=lambda cfg: cfg.mode.stage1.lr),
     StageSpec("B2", demo_share=lambda cfg: cfg.mode.stage2.demo_fraction, fresh_optimizer=True,
               terms=lambda cfg: _margin(cfg.mode.stage2.margin_weight, cfg.mode.stage1.margin),
               exploration=lambda cfg: (cfg.mode.stage2.eps_start, cfg.mode.stage2.eps_end,
                                        cfg.mode.stage2.eps_decay_frames))),
    reads=("name", *DEMOS, "sampling", "stage1", "stage2"),
    check=_check_b))
"""Mode B: stage 1 (``B1``) trains on prior knowledge alone until its checks stop it; stage 2
(``B2``) starts from its weights with a fresh Adam and trains as Default, keeping
``stage2.demo_fraction`` of the buffer for the prior knowledge with the margin loss on it
(0 / 0: the paper's B)."""
