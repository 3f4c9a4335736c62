"""Modes as declared units: a toy mode added from this file alone trains and resumes exactly;
the paper's modes are declared once and everything else asks the registry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest
import torch
from hydra.core.config_store import ConfigStore

from memrl.checkpoint import resume as ckpt
from memrl.data.recipe import DemoRecipe
from memrl.dqn.loop import Trainer
from memrl.losses import MarginTerm, TDTerm
from memrl.modes import HEAD_TD, MODES, DefaultModeConfig, ModeSpec, StageSpec, by_label, register_mode, used
from memrl.schemas import STUDY_MODES
from memrl.train import train
from tests.helpers import (
    TINY,
    assert_same_final_weights_and_agent_buffers,
    csv_rows,
    tiny_mode,
    train_killed_after,
)


@dataclass
class ToyModeConfig:
    """The toy mode's ``mode`` node: its keys and their defaults."""

    name: str = "toy"
    demos_path: Any = None
    example: DemoRecipe = field(default_factory=DemoRecipe)
    sampling: str = "stratified"


@pytest.fixture
def toy_mode():
    """``toy``: one online stage whose buffer keeps half of it for the prior knowledge, with a
    margin term of weight 1 and its own epsilon schedule. Its schema, its stage list and its
    ``+mode=toy`` (what ``conf/mode/toy.yaml`` would hold) are all there is to it."""
    spec = register_mode(ModeSpec(
        "toy", "Toy",
        (StageSpec("toy_online", demo_share=lambda m: 0.5,
                   terms=lambda m: (HEAD_TD, MarginTerm(1.0, 0.5)),
                   exploration=lambda m: (0.5, 0.05, 300)),),
        schema=ToyModeConfig))
    ConfigStore.instance().store(group="mode", name="toy", package="_global_",
                                 node={"defaults": [{"override /mode_schema": "toy"}]})
    yield spec
    del MODES["toy"]


def test_a_toy_mode_from_this_file_trains_and_resumes_after_a_kill(compose_cfg, tmp_path, demos,
                                                                   monkeypatch, toy_mode):
    extra = ["+mode=toy", "total_episodes=6", "checkpoint_every=2"]
    cfg = compose_cfg("train", TINY + extra)
    full = train(cfg, tmp_path / "full", demos=demos)
    assert full.mode == "toy" and full.stage == "toy_online"
    updates = csv_rows(tmp_path / "full" / "updates.csv")
    # the stage's recipe: exactly half of each batch of 8 is prior knowledge (stratified)
    assert updates and {(r["demo_count_min"], r["demo_count_max"]) for r in updates} == {("4", "4")}
    assert {r["stage"] for r in csv_rows(tmp_path / "full" / "episodes.csv")} == {"toy_online"}
    # its epsilon schedule: 0.5 at the start, down to 0.05 after 300 env steps
    first = csv_rows(tmp_path / "full" / "episodes.csv")[0]
    assert 0.05 < float(first["epsilon"]) <= 0.5

    train_killed_after(monkeypatch, cfg, tmp_path / "cut", demos, episodes=5)
    resumed = train(compose_cfg("train", TINY + extra + [f"resume={tmp_path / 'cut'}"]), demos=demos)
    assert resumed.resumed_from_episode == 4
    for key in ("frames", "episodes", "updates", "stage"):
        assert getattr(resumed, key) == getattr(full, key), key
    assert csv_rows(tmp_path / "cut" / "episodes.csv") == csv_rows(tmp_path / "full" / "episodes.csv")
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")
    # what the run reads is what the mode declares: other modes' keys are not part of it
    assert set(used(ckpt.comparable(cfg))["mode"]) == {"name", "demos_path", "example", "sampling"}


def test_the_toy_mode_needs_prior_knowledge_and_names_its_row(toy_mode):
    assert toy_mode.needs_demos and not toy_mode.pretrains
    assert toy_mode.overrides == ("+mode=toy",) and by_label("Toy") is toy_mode


def test_the_paper_modes_are_declared_once():
    assert [m.label for m in MODES.values()][:4] == ["Default", "A", "B", "R"]
    assert list(STUDY_MODES) == [m.label for m in MODES.values()]  # the study takes every mode
    assert [s.name for s in MODES["B"].stages] == ["B1", "B2"]
    assert MODES["B"].pretrains and not MODES["A"].pretrains and not MODES["default"].needs_demos
    assert MODES["B"].next_stage("B1") is MODES["B"].stages[1]
    assert MODES["B"].stages[1].fresh_optimizer and not MODES["A"].stages[0].fresh_optimizer
    with pytest.raises(ValueError, match="taken by another mode"):
        register_mode(ModeSpec("other", "Other", (StageSpec("B1"),), DefaultModeConfig))
    with pytest.raises(ValueError, match="field name: str = 'other'"):  # schema of another mode
        register_mode(ModeSpec("other", "Other", (StageSpec("other1"),), DefaultModeConfig))
    assert "other" not in MODES


def test_an_unknown_mode_is_refused_naming_the_key(compose_cfg, tmp_path):
    from memrl.errors import UserError

    cfg = compose_cfg("train", TINY)
    cfg.mode.name = "nope"
    with pytest.raises(UserError, match="config 'mode.name': unknown mode 'nope'"):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_augment_shift_moves_a_stack_as_one_within_its_bound():
    from memrl.dqn.augment import random_shift

    gen = torch.Generator().manual_seed(0)
    # each frame of a stack is a ramp along one axis plus its frame index: a shift by (dy, dx)
    # reads, inside the image, value(y + dy - s, x + dx - s); the border repeats
    y = torch.arange(84).view(84, 1).expand(84, 84)
    x = torch.arange(84).view(1, 84).expand(84, 84)
    base = torch.stack([(y + 100 * (f % 2)) for f in range(4)]).to(torch.uint8)  # rows
    cols = torch.stack([(x + 100 * (f % 2)) for f in range(4)]).to(torch.uint8)
    batch = torch.stack([base] * 16 + [cols] * 16)  # [32, 4, 84, 84]
    s = 4
    out = random_shift(batch, s, gen)
    assert out.shape == batch.shape and out.dtype == torch.uint8
    seen = set()
    for i in range(32):
        # the shift read from the middle pixel, the same for all 4 frames of the stack
        d = [int(out[i, f, 42, 42]) - int(batch[i, f, 42, 42]) for f in range(4)]
        assert len(set(d)) == 1 and -s <= d[0] <= s
        seen.add(d[0])
        axis_ramp = (base if i < 16 else cols)[0].to(torch.int64)
        want = (axis_ramp + d[0]).clamp(0, 83)  # interior values, the border replicated
        assert torch.equal(out[i, 0].to(torch.int64), want)
    assert len(seen) > 3  # offsets vary between stacks
    assert torch.equal(random_shift(batch, 0, gen), batch)


def test_augment_shifts_sampled_batches_only_and_runs_repeat_exactly(compose_cfg, tmp_path, demos):
    """With shifts the loss differs from the unshifted one; two runs of one seed are equal
    (the learner's own generator), and the stored transitions are never shifted."""
    from memrl.dqn.learner import Learner

    cfg = compose_cfg("train", TINY + ["agent.augment_shift=4"])
    learner = Learner(cfg.agent, seed=0)
    batch = demos[:8].clone()
    plain = Learner(compose_cfg("train", TINY).agent, seed=0)
    plain.loss_module.load_state_dict(learner.loss_module.state_dict())
    before = batch["pixels"].clone()
    assert not torch.equal(learner.loss(batch), plain.loss(batch))
    assert torch.equal(batch["pixels"], before)
    a = train(cfg, tmp_path / "a", demos=demos)
    b = train(cfg, tmp_path / "b", demos=demos)
    assert a.updates == b.updates > 0
    losses = [[r["loss"] for r in csv_rows(tmp_path / run / "updates.csv")] for run in ("a", "b")]
    assert losses[0] == losses[1] and len(losses[0]) > 1


SHORT = ["total_frames=null", "total_episodes=2", "env.duration=30", "agent.warmup_frames=20",
         "agent.batch_size=8", "buffer.capacity=400", "checkpoint_every=1", "progress=false",
         "logger=none", "log_every=5"]


def reference_margin_weight(cfg, stage: str) -> float:
    """The margin weight each stage used before modes were declared (the old builder's rule)."""
    m = cfg.mode
    return {"default": lambda: 0.0, "A": lambda: float(m.margin_weight),
            "B1": lambda: float(m.stage1.margin_weight),
            "B2": lambda: float(m.stage2.margin_weight) if m.stage2.demo_fraction > 0 else 0.0}[stage]()


@pytest.mark.parametrize("preset", [["+experiment=smoke"], ["+experiment=paper"]])
@pytest.mark.parametrize("mode", [None, "A", "B"])
def test_the_stage_losses_equal_the_formula_before_loss_terms(compose_cfg, tmp_path, demos, monkeypatch,
                                                             preset, mode):
    """Today's defaults and the paper preset: every update's loss equals 1/2 TorchRL's l2
    double-DQN loss plus the old builder's margin weight times DQfD's margin loss, recomputed
    from the weights before the update on the same batch (bit for bit)."""
    from memrl.dqn.learner import Learner

    cfg = compose_cfg("train", preset + SHORT + tiny_mode(mode))
    seen: list[tuple[str, dict, object, float]] = []
    original = Learner._eager_grad_step

    def spy(self, batch):
        weights = {k: v.clone() for k, v in self.loss_module.state_dict().items()}
        loss = original(self, batch)
        if len(seen) < 40:
            seen.append((trainer_stage[0], weights, batch.clone(), float(loss)))
        return loss

    trainer_stage = ["?"]
    original_set = Trainer._set_stage

    def set_stage(self, name, fresh_optimizer=False):
        trainer_stage[0] = name
        original_set(self, name, fresh_optimizer)

    monkeypatch.setattr(Learner, "_eager_grad_step", spy)
    monkeypatch.setattr(Trainer, "_set_stage", set_stage)
    train(cfg, tmp_path, demos=demos)
    assert {s for s, *_ in seen} == ({"B1", "B2"} if mode == "B" else {mode or "default"})
    reference = Learner(cfg.agent)
    for stage, weights, batch, loss in seen:
        reference.loss_module.load_state_dict(weights)
        with torch.no_grad():
            expected = 0.5 * reference.loss_module(batch)["loss"]
            w = reference_margin_weight(cfg, stage)
            demo = batch["is_demo"].reshape(-1)
            if w > 0 and bool(demo.any()):
                q = reference.qnet(batch["pixels"][demo])
                a = batch["action"][demo].reshape(-1, 1)
                margin = cfg.mode.margin if "margin" in cfg.mode else cfg.mode.stage1.margin  # A, R / B
                margins = torch.full_like(q, float(margin)).scatter_(-1, a, 0.0)
                expected = expected + w * ((q + margins).max(-1).values - q.gather(-1, a).squeeze(-1)).mean()
        assert float(expected) == loss, stage


def test_a_demo_only_batch_costs_one_online_forward_and_keeps_the_margin_gradient(demos):
    """Mode B's stage 1 (every row a demo): the margin term reuses the TD term's Q(s, .), so
    the network runs 3 times per loss (online s, online s', target s'), not 4; the loss is the
    same value and the gradient the same up to float32 summation order."""
    from memrl.dqn.config import AgentConfig
    from memrl.dqn.learner import Learner

    torch.manual_seed(0)
    learner = Learner(AgentConfig(precision="float32"))
    learner.start_stage((TDTerm(), MarginTerm(3.0, 0.8)))
    batch = demos[:16].clone()
    assert bool(batch["is_demo"].all())
    calls = []
    handle = learner.qnet.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    loss = learner.loss(batch)
    handle.remove()
    assert calls == [16, 16, 16]
    loss.backward()
    shared = {n: p.grad.clone() for n, p in learner.qnet.named_parameters()}
    learner.qnet.zero_grad(set_to_none=True)
    # the two-forward formula: eq. (1) and the margin loss on its own forward of the demo rows
    separate = 0.5 * learner.loss_module(batch)["loss"] + MarginTerm(3.0, 0.8)(
        batch, learner.q_functions(batch))
    assert float(separate) == float(loss)
    separate.backward()
    for name, p in learner.qnet.named_parameters():
        assert torch.allclose(p.grad, shared[name], rtol=1e-4, atol=1e-7), name


SCHEMA_KEYS = {
    "default": {"name"},
    "A": {"name", "demos_path", "example", "demo_fraction", "margin_weight", "margin", "sampling"},
    "B": {"name", "demos_path", "example", "sampling", "stage1", "stage2"},
}
"""Each paper mode's top-level ``mode`` keys."""


@pytest.mark.parametrize("preset", [None, "paper", "smoke", "imitation"])
@pytest.mark.parametrize("mode", ["default", "A", "B"])
def test_the_mode_node_holds_only_the_selected_modes_keys_in_either_order(compose_cfg, mode, preset):
    """The composed ``mode`` node is the mode's own schema: its keys and no other, typed by its
    dataclass; ``+mode`` and ``+experiment`` give the same node in either order."""
    from omegaconf import OmegaConf

    sel = list(MODES[mode].overrides)
    exp = [f"+experiment={preset}"] if preset else []
    first, second = (compose_cfg("train", order) for order in (sel + exp, exp + sel))
    assert set(first.mode) == SCHEMA_KEYS[mode]
    assert OmegaConf.get_type(first.mode) is MODES[mode].schema
    assert OmegaConf.to_container(first) == OmegaConf.to_container(second)
    # the preset's values of the mode's keys (ModeSpec.presets) are there, whatever the order
    if preset == "paper" and mode != "default":
        assert first.mode.example.episodes == 10
        assert (first.mode.margin_weight if mode == "A" else first.mode.stage2.margin_weight) == 0
    if preset == "paper" and mode == "B":
        assert first.mode.stage2.eps_decay_frames == 1_000_000 and first.mode.stage1.lr is None
    if preset == "smoke" and mode != "default":
        assert first.mode.example.episodes == 12
    if preset == "smoke" and mode == "B":
        assert first.mode.stage1.max_updates == 200 and first.mode.stage2.eps_decay_frames == 1500
    if preset == "imitation" and mode == "B":
        assert first.mode.stage1.drive_target == 0.75 and first.mode.stage1.max_updates == 20000
    if preset is None and mode == "B":
        assert first.mode.stage1.drive_target == 0.875 and first.mode.stage1.max_updates == 30000


@pytest.mark.parametrize(("overrides", "line"), [
    (["mode.stage1.lr=1e-3"],
     "config 'mode.stage1.lr': mode default has no such key (mode B's key: add +mode=B)"),
    (["+experiment=paper", "mode.demo_fraction=0.2"],
     "config 'mode.demo_fraction': mode default has no such key (mode A and R's key: add +mode=A "
     "or +mode=R)"),
    (["+mode=A", "mode.stage2.eps_start=0.5"],
     "config 'mode.stage2.eps_start': mode A has no such key (mode B's key: add +mode=B)"),
    (["+mode=B", "mode.margin_weight=0"],
     "config 'mode.margin_weight': mode B has no such key (mode A and R's key: add +mode=A or "
     "+mode=R)"),
    (["mode.example.episodes=3"],
     "config 'mode.example.episodes': mode default has no such key (mode A, B and R's key: add "
     "+mode=A or +mode=B or +mode=R)"),
])
def test_a_key_of_another_mode_is_refused_in_one_line_naming_the_mode_that_has_it(
        compose_cfg, overrides, line):
    from hydra.errors import HydraException

    from memrl.errors import one_line

    with pytest.raises(HydraException) as err:
        compose_cfg("train", overrides)
    assert one_line(err.value) == line


def test_a_study_gives_each_mode_only_its_own_mode_keys():
    """A study's train overrides apply to every mode: each keeps the ``mode`` keys it has; a
    key that no mode has is kept (composition refuses it, naming it)."""
    given = ["seed=1", "mode.stage1.max_updates=4", "mode.demo_fraction=0.2", "mode.example.episodes=3",
             "mode.stage1.margin=0.5", "mode.stage1.nokey=1"]
    assert MODES["default"].own_overrides(given) == ["seed=1", "mode.stage1.nokey=1"]
    assert MODES["A"].own_overrides(given) == ["seed=1", "mode.demo_fraction=0.2", "mode.example.episodes=3",
                                              "mode.stage1.nokey=1"]
    assert MODES["B"].own_overrides(given) == ["seed=1", "mode.stage1.max_updates=4",
                                              "mode.example.episodes=3", "mode.stage1.margin=0.5",
                                              "mode.stage1.nokey=1"]
