"""Training modes as declared units: a mode is its list of stages, and nothing else names it.

Each mode (:class:`ModeSpec`) is declared once, here (Default, A, B) or from any module with
:func:`register_mode` (a test adds a toy mode from its own file): its config name and Table III
label, its config schema (a dataclass: the keys of its ``mode`` node, their types and defaults;
the composed ``mode`` node holds these keys and no other), its range checks and its stages in
order. Each stage
(:class:`StageSpec`) gives its buffer recipe (the share the prior knowledge holds), its
exploration, its loss terms (:mod:`memrl.losses`), its optimizer settings and its stop
rule: an online stage runs until the run's budget; an offline stage (prior knowledge only,
no env steps) until its checks stop it (:mod:`memrl.dqn.stage1`, settings in
``mode.<settings>``), then the next stage starts from its weights.

The trainer, the checkpoints, the records, the reports and the study ask this registry; none of
them branches on a mode or stage name. Importing this module does not import torch.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass, replace
from functools import cache
from typing import Any, get_type_hints

from memrl.data.recipe import DemoRecipe
from memrl.errors import EXPLAINERS, config_error
from memrl.fields import SEED_MAX, spec

Mode = Any
"""A run's composed ``mode`` node (a DictConfig of its mode's schema)."""


class HeadTD:
    """Stands for the value head's own TD term in a stage's ``terms``: the builder puts there
    the term the network declares (``td_term``: eq. (1) for Table I, cross-entropy for C51 and
    HL-Gauss), so a mode names no head and a head no mode."""

    name = "td"

    def __repr__(self) -> str:
        return "HEAD_TD"


HEAD_TD = HeadTD()
"""The value head's own TD term, as a stage lists it (``(HEAD_TD, MarginTerm(...))``)."""


@dataclass(frozen=True)
class StageSpec:
    """One stage of a mode. Each callable receives the run's ``mode`` node (its mode's schema,
    :attr:`ModeSpec.schema`) and nothing else: what a stage reads is its mode's keys; None
    where it returns one means "the ``agent`` node's value"."""

    name: str
    """Its tag in checkpoints, ``episodes.csv`` and ``updates.csv`` (unique over all modes)."""
    demo_share: Callable[[Mode], float] = lambda m: 0.0
    """Share of the buffer (and of each stratified batch) the prior knowledge holds in an
    online stage (0: the agent's data only)."""
    terms: Callable[[Mode], tuple[Any, ...]] = lambda m: (HEAD_TD,)
    """Its loss terms, summed in order (:mod:`memrl.losses`); :data:`HEAD_TD` stands for the
    value head's own TD term (a stage without it trains on its other terms alone)."""
    exploration: Callable[[Mode], tuple[float, float, int] | None] = lambda m: None
    """Epsilon schedule (start, end, decay env steps) of an online stage (None: ``agent``'s
    ``eps_start``, ``eps_end``, ``eps_decay_frames``)."""
    lr: Callable[[Mode], float | None] = lambda m: None
    """Its own Adam learning rate (None: the optimizer's, ``agent.lr`` at first)."""
    n_step: Callable[[Mode], int | None] = lambda m: None
    """Steps summed per sampled transition in its buffer (None: ``agent.n_step``)."""
    updates_per_round: Callable[[Mode], int | None] = lambda m: None
    """Gradient updates per round of an online stage (None: ``agent.updates_per_round``)."""
    fresh_optimizer: bool = False
    """Starts a new Adam at ``agent.lr`` (the weights carry over; the target network is
    synced to them)."""
    teacher: Callable[[Mode], Any] = lambda m: None
    """Its teacher's settings (an online stage after an offline one: the frozen offline-stage
    network, :class:`TeacherConfig`; :mod:`memrl.dqn.teacher`), None: no teacher."""
    settings: str | None = None
    """Makes it an offline stage: it trains on prior knowledge alone (no env steps) until its
    stop rule (:mod:`memrl.dqn.stage1`) stops it, with the settings in the ``mode`` key of
    this name (:class:`Stage1Config`); its weights are then saved (``checkpoints/stage1.pt``,
    :data:`memrl.checkpoint.networks.OFFLINE_WEIGHTS`) and the next stage starts from them.
    None: an online stage, run until the run's budget."""

    @property
    def offline(self) -> bool:
        """Trains on prior knowledge alone, no env steps (it has stop-rule ``settings``)."""
        return self.settings is not None


@dataclass(frozen=True)
class ModeSpec:
    """A training mode: its stages and what it reads."""

    name: str
    """Its ``mode.name`` (``+mode=<name>``; ``default`` needs no ``+mode``)."""
    label: str
    """Its Table III row label."""
    stages: tuple[StageSpec, ...]
    schema: type
    """Its ``mode`` node: a dataclass whose fields are its keys (``name`` defaults to its name),
    registered as ``mode_schema/<name>`` (:func:`memrl.configs.register_configs`); ``+mode=<name>``
    selects it (``conf/mode/<name>.yaml``). Its values are checked as every schema's
    (:func:`memrl.fields.check_fields`): the ranges on its fields, then its static
    ``check(node, prefix)`` for rules across its keys."""
    overrides: tuple[str, ...] = field(default=())
    """Command-line overrides that select it (``+mode=A``); filled in by :func:`register_mode`."""
    renamed: dict[str, str] = field(default_factory=dict)
    """Keys its ``mode`` node had under another name in earlier versions: old dotted key -> its
    key now (mode A: ``stage1.margin`` -> ``margin``); :meth:`used` reads an older run's value
    under the new name, so it resumes and shares report rows with a new one."""
    presets: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Its values under each preset (``+experiment=<preset>``): preset name -> ``mode`` values,
    registered as ``mode_preset/<name>_<preset>`` (:func:`memrl.configs.register_configs`) and
    merged last (``conf/train.yaml``), so a mode needs no preset file and ``+mode`` and
    ``+experiment`` work in either order."""

    @property
    def reads(self) -> tuple[str, ...]:
        """The top-level ``mode`` keys it has (its schema's fields): the only ones it reads."""
        return tuple(f.name for f in fields(self.schema))

    def has_key(self, dotted: str) -> bool:
        """Whether its ``mode`` node has the key ``dotted`` (``stage1.lr``; no ``mode.``)."""
        return _schema_at(self.schema, dotted.split(".")) is not None

    def own_overrides(self, overrides: list[str]) -> list[str]:
        """``overrides`` less those of a ``mode`` key that it lacks and another mode has: a
        study's train overrides and variants apply to every mode, each takes its own keys (a
        key no mode has is kept: composition refuses it, naming it)."""
        def foreign(override: str) -> bool:
            key = override.lstrip("~+").partition("=")[0]
            if not key.startswith("mode."):
                return False
            key = key.removeprefix("mode.")
            return not self.has_key(key) and any(m.has_key(key) for m in MODES.values())

        return [o for o in overrides if not foreign(str(o))]

    @property
    def needs_demos(self) -> bool:
        """Reads prior knowledge: some stage keeps demos in its buffer (``demos_path`` read)."""
        return "demos_path" in self.reads

    @property
    def pretrains(self) -> bool:
        """Has an offline stage, whose weights are saved (``checkpoints/stage1.pt``)."""
        return self.offline_stage is not None

    @property
    def offline_stage(self) -> StageSpec | None:
        """Its offline stage (prior knowledge alone), if it has one."""
        return next((s for s in self.stages if s.offline), None)

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
        """The values of ``mode`` this mode reads (a plain ``mode`` dict, of this run or of a run
        made when the ``mode`` node held every mode's keys): its schema's keys, nested ones
        included, the others dropped; ``example`` only where ``demos_path`` is null (the dataset
        is recorded from it), with its defaults filled in."""
        from memrl.data.recipe import recipe_values

        out = _project(self.schema, _renamed(mode, self.renamed))
        if "example" in out:
            if out.get("demos_path") is None:
                out["example"] = recipe_values(out["example"])
            else:
                del out["example"]
        return out


def _renamed(mode: dict[str, Any], renamed: dict[str, str]) -> dict[str, Any]:
    """``mode`` with each old key's value under its new name (where the new one is absent)."""
    out = copy.deepcopy(mode)
    for old, new in renamed.items():
        *parents, leaf = old.split(".")
        node: Any = out
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            continue
        value = node.pop(leaf)
        *new_parents, new_leaf = new.split(".")
        target = out
        for part in new_parents:
            target = target.setdefault(part, {})
        target.setdefault(new_leaf, value)
    return out


@cache
def _hints(schema: type) -> dict[str, Any]:
    """Field name -> its resolved type, for a schema dataclass."""
    hints = get_type_hints(schema)
    return {f.name: hints[f.name] for f in fields(schema)}


def _project(schema: type, node: dict[str, Any]) -> dict[str, Any]:
    """``node`` with only the keys of ``schema``, recursing into its nested schemas (not into
    ``example``, a recipe whose values :func:`memrl.data.recipe.recipe_values` fills)."""
    out: dict[str, Any] = {}
    for key, typ in _hints(schema).items():
        if key not in node:
            continue
        value = node[key]
        nested = is_dataclass(typ) and typ is not DemoRecipe and isinstance(value, dict)
        out[key] = _project(typ, value) if nested else value  # type: ignore[arg-type]
    return out


MODES: dict[str, ModeSpec] = {}
"""Every declared mode by its ``mode.name``."""


def register_mode(spec: ModeSpec) -> ModeSpec:
    """Declare a mode (replacing one of the same name); its stage names must be new."""
    taken = {s.name for m in MODES.values() if m.name != spec.name for s in m.stages}
    clash = sorted(taken & {s.name for s in spec.stages})
    if clash:
        raise ValueError(f"mode {spec.name}: stage names {clash} are taken by another mode")
    named = {f.name: f.default for f in fields(spec.schema)} if is_dataclass(spec.schema) else {}
    if named.get("name") != spec.name:
        raise ValueError(f"mode {spec.name}: its schema {getattr(spec.schema, '__name__', spec.schema)} "
                         f"must be a dataclass with a field name: str = {spec.name!r}")
    overrides = () if spec.name == "default" else (f"+mode={spec.name}",)
    MODES[spec.name] = replace(spec, overrides=overrides)
    return MODES[spec.name]


def mode_of(cfg_or_name: Any) -> ModeSpec:
    """The mode of a train config (or of a ``mode.name``)."""
    name = cfg_or_name if isinstance(cfg_or_name, str) else str(cfg_or_name.mode.name)
    if name not in MODES:
        raise config_error("mode.name", f"unknown mode {name!r} (declared: {', '.join(MODES)})")
    return MODES[name]


def by_label(label: str) -> ModeSpec:
    """The mode whose Table III label is ``label``."""
    for mode in MODES.values():
        if mode.label == label:
            return mode
    raise KeyError(f"no mode labelled {label!r} (labels: {[m.label for m in MODES.values()]})")


def used(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (a plain train config) with only the ``mode`` keys its mode reads: a setting a
    run never used cannot stop it from resuming, nor split a report row."""
    mode = config.get("mode")
    if not isinstance(mode, dict) or mode.get("name") not in MODES:
        return config
    return {**config, "mode": MODES[str(mode["name"])].used(mode)}


def explain_key_error(err: BaseException) -> str | None:
    """One line for a command-line key of a mode that is not selected (``mode.stage1.lr=1e-3``
    without ``+mode=B``): which mode has it and how to select it; None for any other error.
    Hooked into :func:`memrl.errors.one_line`."""
    m = re.match(r"Could not (?:override|append to) '(?:\+{0,2})(mode\.[^']+)'", str(err))
    if m is None:
        return None
    key = m.group(1)
    owners = [s for s in MODES.values() if s.has_key(key.removeprefix("mode."))]
    # a mode whose schema extends another owner's (qdagger of B) has the key by inheritance
    owners = [o for o in owners if not any(p is not o and issubclass(o.schema, p.schema) for p in owners)]
    if not owners:
        return None
    cause = err.__cause__
    where = str(getattr(cause, "full_key", "") or "").split(".")[1:-1]  # the node that lacks it
    otype = getattr(cause, "object_type", None)
    now = [s.name for s in MODES.values() if otype is not None and _schema_at(s.schema, where) is otype]
    which = f"mode {now[0]}" if len(now) == 1 else "the selected mode"
    how = " or ".join(o.overrides[0] if o.overrides else "no +mode" for o in owners)
    names = [o.name for o in owners]
    whose = names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"
    return f"config '{key}': {which} has no such key (mode {whose}'s key: add {how})"


def _schema_at(schema: Any, path: list[str]) -> Any:
    """The type at ``path`` inside a schema dataclass (a nested schema or a leaf's type); None
    where the path leaves the schema."""
    for part in path:
        if schema is None or not is_dataclass(schema):
            return None
        schema = _hints(schema).get(part)
    return schema


EXPLAINERS.append(explain_key_error)


# ------------------------------------------------------------------ Default, A and B (the paper)
def _td_and_margin(weight: float, margin: float) -> tuple[Any, ...]:
    """The head's TD term, then DQfD's margin term where its weight is positive."""
    from memrl.losses import margin_terms

    return (HEAD_TD, *margin_terms(float(weight), float(margin)))


def _need(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise config_error(key, message)


SAMPLINGS = ("stratified", "proportional")
"""How a batch splits between the prior knowledge and the agent's data (:mod:`memrl.data.buffers`)."""
CRITERIA = ("agreement", "plateau", "agreement_or_plateau", "behaviour", "max_updates")
"""The offline stage's stop rules (:mod:`memrl.dqn.stage1`)."""


@dataclass
class Stage1Config:
    """Mode B stage 1: train on prior knowledge only, until behaviour converges.

    The defaults are those with which stage 1 learned the lane change from the default prior
    knowledge (docs/results/stage1-slow-check.md; docs/training.md, "Presets"): its own Adam at
    1e-3, DQfD's margin loss at weight 3, and every 1,000 updates 40 greedy drives that stop it
    at 35 of them (else at 30,000 updates) and keep the best weights: 78% of non-goal test
    episodes survived and reached the target, 3 seeds (docs/results/issue20, section 6;
    stopping at 75% within 20,000 updates gave 63%). ``+experiment=paper``: eq. (1) alone."""

    max_updates: int = spec(30_000, ge=1)
    """Hard cap on stage-1 updates."""
    check_every: int = spec(1000, ge=1)
    """Updates between convergence checks."""
    holdout_fraction: float = spec(0.1, gt=0, lt=1)
    """Share of demo transitions kept out of the buffer to measure action agreement."""
    agreement: float = spec(0.9, gt=0, le=1)
    """Stop when the greedy action equals the demo action on this share of held-out demos."""
    plateau_checks: int = spec(4, ge=1)
    """Stop when the mean TD loss improved less than ``plateau_tol`` (relative) over this many checks."""
    plateau_tol: float = spec(0.02, ge=0, lt=1)
    """Relative loss improvement under which the loss counts as flat."""
    criterion: str = spec("behaviour", choices=CRITERIA)
    """agreement | plateau | agreement_or_plateau | behaviour | max_updates. ``behaviour``:
    stop when ``drive_target`` of the drive episodes survive and reach the target lane."""
    drive_episodes: int = spec(40, ge=0)
    """Greedy non-goal episodes driven at every check (0: none): the behaviour itself, in
    scenes of their own seed domain (not the test scenes). Needed by ``behaviour``."""
    drive_seed: int = spec(0, ge=0, le=SEED_MAX)
    """Base of the drive episodes' scene seeds."""
    drive_target: float = spec(0.875, gt=0, le=1)
    """``behaviour``: share of drive episodes that must both survive and reach the target (35 of
    40: the drives still rose past 30 of 40, the earlier target 0.75)."""
    keep_best: bool = True
    """With drive episodes: stage 2 (and ``stage1.pt``) start from the checked weights that
    drove best (most episodes surviving and reaching; ties: the later), not the last ones.
    Imitation from few demos swings from check to check (docs/results/stage1-slow-check.md)."""
    margin_weight: float = spec(3.0, ge=0)
    """Weight of DQfD's large-margin loss on the demos in stage 1 (0: eq. (1) alone, the
    paper's literal reading; with it alone the greedy agent drifts away from the demo actions,
    see docs/results/stage1-slow-check.md)."""
    margin: float = spec(0.8, ge=0)
    """Margin of that loss [Q units]."""
    lr: float | None = spec(1e-3, gt=0)
    """Adam learning rate of stage 1 (None: ``agent.lr``). Stage 2 starts a fresh Adam at
    ``agent.lr`` whatever this is. At 2.5e-4 stage 1 learned the steering too slowly
    (docs/results/stage1-slow-check.md)."""
    init: Any = None
    """A mode B run folder (or its ``checkpoints/stage1.pt``) whose stage-1 weights this run's
    stage 2 starts from, training no stage 1 of its own: one pretraining shared by stage-2
    variants (exploration, budgets, ...). Its env config must equal this run's; its network this
    run's, this run's base head (``network=risk``) or, for a categorical head, Table I's of the
    same trunk (its output layer converted: docs/network.md). The run's own
    ``checkpoints/stage1.pt`` is a copy. Null: train stage 1 here."""

    @staticmethod
    def check(s1: Any, prefix: str = "mode.stage1.") -> None:
        """Rules across its keys: a stop rule that can stop it, checks it can make."""
        _need(s1.criterion != "behaviour" or s1.drive_episodes >= 1, f"{prefix}drive_episodes",
              "criterion 'behaviour' needs drive episodes (>= 1)")
        _need(s1.criterion == "max_updates" or s1.check_every <= s1.max_updates, f"{prefix}check_every",
              f"{s1.check_every} updates between checks is more than {prefix}max_updates "
              f"({s1.max_updates}): stage 1 would stop before its first check")
        _need(s1.criterion != "plateau" or (s1.plateau_checks + 1) * s1.check_every < s1.max_updates,
              f"{prefix}plateau_checks", f"a window of {s1.plateau_checks} checks needs "
              f"{s1.plateau_checks + 1} checks of {s1.check_every} updates, not fewer than "
              f"{prefix}max_updates ({s1.max_updates}): the plateau rule could never stop stage 1")


@dataclass
class Stage2Config:
    """Mode B stage 2: double DQN from the stage-1 weights; by default the prior knowledge
    stays at 10% of its buffer and batches with the margin loss on it (DQfD), which kept most
    of what stage 1 learned (without it both scores dropped after the switch).
    ``+experiment=paper``: plain double DQN as Default."""

    eps_start: float = spec(0.3, ge=0, le=1)
    """Stage 2 starts less random than a fresh agent: the stage-1 network already drives."""
    eps_end: float = spec(0.05, ge=0, le=1)
    """Final epsilon."""
    eps_decay_frames: int = spec(50_000, ge=1)
    """Env steps of the linear decay."""
    demo_fraction: float = spec(0.1, ge=0, lt=1)
    """Share of stage 2's buffer (and of each stratified batch) that the prior knowledge keeps
    holding, as in mode A (0: none, the paper's B: stage 2 trains as Default)."""
    margin_weight: float = spec(3.0, ge=0)
    """Weight of stage 1's large-margin loss (``stage1.margin``) on the demo items of stage 2's
    batches, DQfD's remedy for the drop after pretraining (0: eq. (1) alone, the paper's B).
    Acts only where ``demo_fraction > 0`` (with 0 no batch holds a demo). With both (0.1,
    3) B kept most of what stage 1 learned: at 20,000 env steps, non-goal survival / goal 77 / 73
    against 23 / 43 without (docs/results/issue20)."""
    lr: float | None = spec(None, gt=0)
    """Adam learning rate of stage 2 (None: ``agent.lr``; stage 1 has its own, ``stage1.lr``).
    A smaller rate changes the stage-1 weights less per update: at 6.25e-5 with
    ``n_step=3`` stage 2 ended above its stage 1 on 3 of 5 seeds, at 2.5e-4 on 1 of 5; with
    n = 1 on 2 of 3 (docs/results/issue30/screens.md, sections 23-24). Those stage 1s were
    trained with n = 3; from the default stage 1 (n = 1) the same recipe ended above it on 1
    of 3 seeds (section 26), so neither is a default."""
    n_step: int | None = spec(None, ge=1)
    """Steps of reward summed per sampled transition in stage 2's buffer, agent data and demos
    alike (None: ``agent.n_step``; stage 1 reads ``agent.n_step``)."""
    updates_per_round: int | None = spec(None, ge=1)
    """Gradient updates per round (every ``agent.train_every`` env steps) in stage 2: its replay
    ratio (None: ``agent.updates_per_round``). The target network is still copied every
    ``agent.target_update_interval`` updates, so more often per env step. At 4 stage 2 ended
    above its stage 1 on 1 of 3 seeds, at 3x the wall time (docs/results/issue30/screens.md,
    section 27), so it is not a default."""

    @staticmethod
    def check(s2: Any, prefix: str = "mode.stage2.") -> None:
        """Rules across its keys: an epsilon that decays."""
        _need(s2.eps_end <= s2.eps_start, f"{prefix}eps_start",
              f"need eps_end <= eps_start, got {s2.eps_start} -> {s2.eps_end}")


@dataclass
class DefaultModeConfig:
    """Default's ``mode`` node: its name alone (no prior knowledge)."""

    name: str = "default"
    """default | A | B (``+mode=A|B``)."""


@dataclass
class DemoKeys:
    """The keys of a mode that reads prior knowledge (A and B: their name first, then these)."""

    name: str = ""
    """default | A | B (``+mode=A|B``)."""
    demos_path: Any = None
    """Dataset folder of prior knowledge (None: the scripted driver's dataset of ``example``)."""
    example: DemoRecipe = field(default_factory=DemoRecipe)
    """How the prior knowledge is recorded when ``demos_path`` is null (recorded on first use,
    cached under ``paths.data_dir``): the manoeuvre-focused recipe by default."""


@dataclass
class ModeAConfig(DemoKeys):
    """Mode A's ``mode`` node (``+mode=A``)."""

    name: str = "A"
    """default | A | B (``+mode=A|B``)."""
    demo_fraction: float = spec(0.1, gt=0, lt=1)
    """Share of the buffer permanently held by prior knowledge."""
    margin_weight: float = spec(3.0, ge=0)
    """Weight of the large-margin loss (``margin``) on the demo items of each batch, as
    DQfD (0: eq. (1) alone, the paper's A); mode B's is ``stage2.margin_weight``. At 20,000 env
    steps A's non-goal goal rose from 0.7 to 19.0 with it, higher on every seed
    (docs/results/issue20)."""
    margin: float = spec(0.8, ge=0)
    """Margin of the large-margin loss [Q units] (older runs: ``stage1.margin``, read as this)."""
    sampling: str = spec("stratified", choices=SAMPLINGS)
    """Stratified (exactly round(demo_fraction x batch) demos per batch) or proportional
    (uniform over the union: the demo count per batch is binomial)."""


@dataclass
class ModeBConfig(DemoKeys):
    """Mode B's ``mode`` node (``+mode=B``)."""

    name: str = "B"
    """default | A | B (``+mode=A|B``)."""
    sampling: str = spec("stratified", choices=SAMPLINGS)
    """Stage 2's batches, where prior knowledge stays in its buffer: stratified (exactly
    round(stage2.demo_fraction x batch) demos per batch) or proportional (binomial count)."""
    stage1: Stage1Config = field(default_factory=Stage1Config)
    stage2: Stage2Config = field(default_factory=Stage2Config)


@dataclass
class ModeRConfig(DemoKeys):
    """Mode R's ``mode`` node (``+mode=R``): RLPD's symmetric sampling (Ball et al., 2023)."""

    name: str = "R"
    """default | A | B | R (``+mode=<name>``)."""
    demo_fraction: float = spec(0.5, gt=0, lt=1)
    """Share of every batch (and of the buffer) that the prior knowledge holds, from the first
    update on (RLPD: half)."""
    sampling: str = spec("stratified", choices=SAMPLINGS)
    """Stratified (exactly round(demo_fraction x batch) demos per batch, RLPD's symmetric
    sampling) or proportional (binomial count)."""
    margin_weight: float = spec(0.0, ge=0)
    """Weight of DQfD's large-margin loss on each batch's demos (0: none, RLPD's own)."""
    margin: float = spec(0.8, ge=0)
    """Margin of that loss [Q units]."""


@dataclass
class TeacherConfig:
    """Stage 2 held to its prior knowledge by the run's own stage-1 network, the teacher (a
    frozen copy of ``checkpoints/stage1.pt``; no expert on call), in three ways that add up
    (each off at 0): QDagger's distillation (Agarwal et al. 2022), JSRL's roll-ins (Uchendu et
    al. 2022) and WSRL's warm start (Zhou et al. 2024). The student's drives (``drive_*``, the
    stage-1 drive scenes) gate the first two; :mod:`memrl.dqn.teacher`."""

    distill_weight: float = spec(0.0, ge=0)
    """QDagger: weight of KL(pi_teacher || softmax(Q / temperature)) on the batch's agent
    states; it is scaled by ``max(0, 1 - student / teacher)`` (their drives that survive and
    reach), never rising again once lowered, so the teacher lets go as the student catches up."""
    temperature: float = spec(1.0, gt=0)
    """tau of both softmaxes [Q units]."""
    roll_in: int = spec(0, ge=0)
    """JSRL: the teacher drives the first h steps of each training episode (greedy), the agent
    the rest; h starts here and steps down by ``roll_in / roll_in_stages`` whenever the
    combined policy drives at least ``tolerance`` x its best so far (at first the teacher's)."""
    roll_in_stages: int = spec(5, ge=1)
    """Steps of the curriculum from ``roll_in`` down to 0."""
    roll_in_random: bool = False
    """JSRL-random: h drawn uniformly from 0..``roll_in`` for each episode, no curriculum."""
    tolerance: float = spec(0.9, gt=0, le=1)
    """The roll-in curriculum's gate: share of the best score so far the combined policy must reach."""
    warm_start: int = spec(0, ge=0)
    """WSRL: env steps (summed over envs) of the frozen teacher's own rollouts (greedy with the
    stage's starting epsilon) that fill the stage's buffer before its first update, in place of
    the random warm-up (``agent.warmup_frames``): no update before both have passed."""
    check_every: int = spec(5000, ge=1)
    """Env steps between the student's drives (distillation and curriculum; none without them)."""
    drive_episodes: int = spec(40, ge=1)
    """Greedy non-goal drives per check, in the stage-1 drive scenes (the teacher drives them once)."""
    drive_seed: int = spec(0, ge=0, le=SEED_MAX)
    """Base of their scene seeds."""


@dataclass
class ModeQDaggerConfig(ModeBConfig):
    """QDagger's ``mode`` node (``+mode=qdagger``): mode B whose stage 2 distils its stage 1."""

    name: str = "qdagger"
    """The mode's name (``+mode=qdagger``)."""
    teacher: TeacherConfig = field(default_factory=lambda: TeacherConfig(distill_weight=1.0))


@dataclass
class ModeJSRLConfig(ModeBConfig):
    """JSRL's ``mode`` node (``+mode=jsrl``): mode B whose stage 1 drives stage 2's first steps."""

    name: str = "jsrl"
    """The mode's name (``+mode=jsrl``)."""
    teacher: TeacherConfig = field(default_factory=lambda: TeacherConfig(roll_in=150))


@dataclass
class ModeWSRLConfig(ModeBConfig):
    """WSRL's ``mode`` node (``+mode=wsrl``): mode B whose stage 2 starts on its stage 1's rollouts."""

    name: str = "wsrl"
    """The mode's name (``+mode=wsrl``)."""
    teacher: TeacherConfig = field(default_factory=lambda: TeacherConfig(warm_start=4800))


SMOKE_DEMOS = {"example": {"episodes": 12}}
"""The smoke preset's prior knowledge: the default recipe, 12 episodes (about 1,000 transitions)."""

PAPER_DEMOS = {"example": {"episodes": 10, "tail_steps": None, "action_noise": 0.0,
                           "driver": {"merge_window": None, "speed_tolerance": None},
                           "env": {"initial_lane": None, "vehicles_count": None}}}
"""The paper preset's prior knowledge: whole, noiseless episodes of lane changes in the training
env's own episodes (the paper records people's drives and gives no count; this is memrl's
example before the manoeuvre-focused recipe)."""

A_PRESETS = {
    "paper": {**PAPER_DEMOS, "margin_weight": 0.0},  # eq. (1) alone on its batches, demos included
    "smoke": SMOKE_DEMOS,
}
"""Mode A's values under ``+experiment=paper`` (eq. (1) alone on its stratified batches, the
paper's demos) and ``+experiment=smoke``."""

B_PRESETS = {
    "paper": {**PAPER_DEMOS,
              # eq. (1) alone in stage 1, one Adam rate (agent.lr) for both stages: the paper names no other
              "stage1": {"margin_weight": 0.0, "lr": None},
              # stage 2 exactly as Default: the same schedule from 1.0, no prior knowledge left in its buffer
              "stage2": {"eps_start": 1.0, "eps_end": 0.05, "eps_decay_frames": 1_000_000,
                         "demo_fraction": 0.0, "margin_weight": 0.0}},
    "smoke": {**SMOKE_DEMOS,
              # 3 of 4 greedy drives surviving and reaching stop stage 1 early
              "stage1": {"max_updates": 200, "check_every": 50, "drive_episodes": 4, "drive_target": 0.75},
              "stage2": {"eps_decay_frames": 1500}},
    # stage 1 with its own faster Adam and a stronger large-margin loss, stopped once 75% of 40
    # greedy non-goal drives survive and reach the target lane (else at 20,000 updates), stage 2
    # from the weights that drove best
    "imitation": {"stage1": {"lr": 0.001, "margin_weight": 3.0, "max_updates": 20000, "check_every": 1000,
                             "criterion": "behaviour", "drive_episodes": 40, "drive_target": 0.75,
                             "keep_best": True}},
}
"""Mode B's values under ``+experiment=paper|smoke|imitation``."""

register_mode(ModeSpec("default", "Default", (StageSpec("default"),), schema=DefaultModeConfig))
"""Default: plain double DQN (eq. (1)), the agent's own data only."""

register_mode(ModeSpec(
    "A", "A",
    (StageSpec("A", demo_share=lambda m: m.demo_fraction,
               terms=lambda m: _td_and_margin(m.margin_weight, m.margin)),),
    schema=ModeAConfig, presets=A_PRESETS, renamed={"stage1.margin": "margin"}))
"""Mode A: prior knowledge permanently holds ``demo_fraction`` of the buffer, stratified
batches, DQfD's margin loss on their demos (weight ``margin_weight``, 0: the paper's A)."""

register_mode(ModeSpec(
    "B", "B",
    (StageSpec("B1", settings="stage1", lr=lambda m: m.stage1.lr,
               terms=lambda m: _td_and_margin(m.stage1.margin_weight, m.stage1.margin)),
     StageSpec("B2", demo_share=lambda m: m.stage2.demo_fraction, fresh_optimizer=True,
               lr=lambda m: m.stage2.lr, n_step=lambda m: m.stage2.n_step,
               updates_per_round=lambda m: m.stage2.updates_per_round,
               terms=lambda m: _td_and_margin(m.stage2.margin_weight, m.stage1.margin),
               exploration=lambda m: (m.stage2.eps_start, m.stage2.eps_end, m.stage2.eps_decay_frames))),
    schema=ModeBConfig, presets=B_PRESETS))
"""Mode B: stage 1 (``B1``) trains on prior knowledge alone until its checks stop it; stage 2
(``B2``) starts from its weights with a fresh Adam and trains as Default, keeping
``stage2.demo_fraction`` of the buffer for the prior knowledge with the margin loss on it
(0 / 0: the paper's B)."""

register_mode(ModeSpec(
    "R", "R",
    (StageSpec("R", demo_share=lambda m: m.demo_fraction,
               terms=lambda m: _td_and_margin(m.margin_weight, m.margin)),),
    schema=ModeRConfig, presets={"smoke": SMOKE_DEMOS}))
"""Mode R: RLPD's symmetric sampling, prior knowledge at half of every batch from the first
update, no offline stage; the margin term optional (``margin_weight``, off). The worked example
of a mode in ``docs/extending.md``: this declaration and ``conf/mode/R.yaml``."""


def _teacher_stages(tag: str) -> tuple[StageSpec, StageSpec]:
    """Mode B's two stages under the names ``<tag>1``, ``<tag>2``, stage 2 with its teacher and
    (QDagger) the distillation term."""
    b1, b2 = MODES["B"].stages
    return (replace(b1, name=f"{tag}1"),
            replace(b2, name=f"{tag}2", teacher=lambda m: m.teacher,
                    terms=lambda m: (*b2.terms(m), *_distill(m.teacher))))


def _distill(teacher: Any) -> tuple[Any, ...]:
    """QDagger's distillation term where ``teacher.distill_weight`` is positive (importing the
    terms, and torch, only when a stage is built)."""
    from memrl.losses import distill_terms

    return tuple(distill_terms(teacher.distill_weight, teacher.temperature))


TEACHER_PRESETS = {k: v for k, v in B_PRESETS.items() if k != "paper"}
"""The teacher modes' presets: mode B's, less ``paper`` (the paper has no teacher)."""

register_mode(ModeSpec("qdagger", "QDagger", _teacher_stages("Q"), schema=ModeQDaggerConfig,
                       presets=TEACHER_PRESETS))
"""QDagger: mode B whose stage 2 adds a distillation term towards its frozen stage 1, its weight
falling to 0 as the student's drives reach the teacher's (``mode.teacher``)."""

register_mode(ModeSpec("jsrl", "JSRL", _teacher_stages("J"), schema=ModeJSRLConfig, presets=TEACHER_PRESETS))
"""JSRL: mode B whose frozen stage 1 drives the first h steps of stage 2's training episodes, h
shrinking on a curriculum gated by the combined policy's drives (``mode.teacher``)."""

register_mode(ModeSpec("wsrl", "WSRL", _teacher_stages("W"), schema=ModeWSRLConfig, presets=TEACHER_PRESETS))
"""WSRL: mode B whose stage 2's buffer is first filled with its frozen stage 1's own rollouts
(``mode.teacher.warm_start`` env steps), in place of the random warm-up."""
