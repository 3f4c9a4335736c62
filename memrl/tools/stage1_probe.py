"""Mode B's first stage-1 updates under a probe: does the network learn or collapse?

``python -m memrl.tools.stage1_probe RUN [updates=400] [every=50] [KEY=VALUE ...]`` builds the
trainer of a run's ``config.yaml`` (RUN: the run folder or the file; ``KEY=VALUE``: OmegaConf
dot-list overrides of it, e.g. ``seed=3`` or ``env.opponent.type=constant 'env.opponent.pool=[]'``),
takes its stage-1 updates on the prior knowledge and, every ``every`` updates, prints the mean
TD loss and what the network does on a fixed probe batch of 256 demo states: dead units per
ReLU layer (a unit no probe state activates), the spread of Q over states, the number of
different greedy actions. The first line fingerprints the initial weights (sha256 of the
network's parameters), so two configs can be checked to start alike.

``weights=final`` (or ``stage1``) trains nothing: it prints the same measures for the run's trained
network (or its stage-1 weights) on 256 states drawn with a generator seeded 0 from the run's prior
knowledge (``demos=PATH``: from that dataset, e.g. for a Default run), with the indices of each
conv layer's dead channels, and its calibration (Cal-QL's diagnosis): Q(s, a_demo) against the
demos' Monte-Carlo returns at ``agent.gamma`` (:mod:`memrl.data.mc_returns`) over every demo
step whose return is known. The probe's rows give the mean Q - return on 256 such steps.

Nothing is written outside a temporary folder. A stage 1 whose units die in its first updates
keeps one greedy action for every state (docs/training.md, mode B).
"""

from __future__ import annotations

import hashlib
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch
from torch import nn

PROBE_STATES = 256
USAGE = ("usage: python -m memrl.tools.stage1_probe RUN [updates=400] [every=50] "
         "[weights=final|stage1] [demos=DATASET] [KEY=VALUE ...]")


@torch.no_grad()
def dead_indices(net: nn.Module, pixels: torch.Tensor) -> list[tuple[bool, list[int]]]:
    """Per ``nn.ReLU`` of ``net`` in forward order: (a conv map, the indices of its units that
    no state of ``pixels`` activates): channels of a conv map, features of a linear layer."""
    dead: list[tuple[bool, list[int]]] = []

    def record(_module: nn.Module, _inputs: Any, out: torch.Tensor) -> None:
        active = (out > 0).flatten(2).any(-1) if out.dim() > 2 else out > 0
        dead.append((out.dim() > 2, torch.nonzero(~active.any(0)).flatten().tolist()))

    hooks = [m.register_forward_hook(record) for m in net.modules() if isinstance(m, nn.ReLU)]
    try:
        net(pixels)
    finally:
        for h in hooks:
            h.remove()
    return dead


def dead_units(net: nn.Module, pixels: torch.Tensor) -> list[int]:
    """Per ``nn.ReLU`` of ``net`` in forward order: how many units no state of ``pixels``
    activates (output 0 everywhere)."""
    return [len(units) for _, units in dead_indices(net, pixels)]


def fingerprint(net: nn.Module) -> str:
    """First 12 hex digits of the sha256 of the network's parameters and buffers, in order."""
    digest = hashlib.sha256()
    for value in net.state_dict().values():
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:12]


@torch.no_grad()
def snapshot(net: nn.Module, pixels: torch.Tensor) -> dict[str, Any]:
    """What the network does on the probe states now."""
    q = net(pixels)
    return {"dead": dead_units(net, pixels), "q_spread": float(q.std(0).mean()),
            "greedy_actions": int(q.argmax(-1).unique().numel())}


def known_returns(td: Any, gamma: float, limit: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rows, G)``: the rows of ``td`` whose Monte-Carlo return is known
    (:func:`memrl.data.mc_returns.mc_returns`) and those returns (``limit``: that many rows,
    drawn with a generator seeded 0)."""
    from memrl.data.mc_returns import mc_returns

    g, known = mc_returns(td, gamma)
    rows = torch.nonzero(known).reshape(-1)
    if limit is not None and len(rows) > limit:
        pick = torch.randperm(len(rows), generator=torch.Generator().manual_seed(0))[:limit]
        rows = rows[pick].sort().values
    return rows, g[rows]


@torch.no_grad()
def calibration(net: nn.Module, td: Any, gamma: float, limit: int | None = None,
                returns: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, Any]:
    """Q(s, a_demo) against the demos' Monte-Carlo returns over the rows whose return is known
    (:func:`known_returns`, or ``returns`` computed by it once): the means of both, of Q - G and
    |Q - G|, the share of rows with Q below G (Cal-QL calls Q calibrated where it is at least the
    data's return) and their correlation."""
    rows, g = known_returns(td, gamma, limit) if returns is None else returns
    if len(rows) == 0:
        return {"states": 0}
    q = torch.cat([net(td["pixels"][part]).gather(-1, td["action"][part].reshape(-1, 1).long()).reshape(-1)
                   for part in rows.split(PROBE_STATES)]).to(torch.float64)
    diff = q - g
    corr = float(torch.corrcoef(torch.stack([q, g]))[0, 1]) if len(rows) > 1 else float("nan")
    return {"states": len(rows), "q": float(q.mean()), "g": float(g.mean()), "bias": float(diff.mean()),
            "abs": float(diff.abs().mean()), "below": float((diff < 0).double().mean()), "corr": corr}


def calibration_line(cal: dict[str, Any]) -> str:
    if not cal["states"]:
        return "calibration: no demo step whose return is known"
    return (f"calibration on {cal['states']} demo steps whose return is known: Q(s, a_demo) {cal['q']:.2f}, "
            f"return {cal['g']:.2f}, Q - return {cal['bias']:+.2f} (|.| {cal['abs']:.2f}), Q below the "
            f"return on {100 * cal['below']:.1f}% of them, correlation {cal['corr']:.3f}")


def probe(cfg: Any, updates: int, every: int, out_dir: Path) -> list[dict[str, Any]]:
    """``updates`` stage-1 updates of the trainer of ``cfg`` (a mode B train config, stage 1
    not yet done); rows at update 0 and every ``every`` updates. Returns the rows (the first
    also has ``init``, the weights' fingerprint)."""
    from memrl.dqn.loop import Trainer
    from memrl.modes import mode_of
    from memrl.train import prior_knowledge

    spec = mode_of(cfg)
    if not spec.stages[0].offline:
        raise ValueError(f"the probe takes a stage 1 on prior knowledge alone; mode {spec.name} "
                         "starts online")
    demos = prior_knowledge(cfg)
    trainer = Trainer(cfg, out_dir, demos=demos)
    net = trainer.learner.qnet
    pixels = torch.cat([trainer.stage.buffer.sample()["pixels"]
                        for _ in range(-(-PROBE_STATES // int(cfg.agent.batch_size)))])[:PROBE_STATES]
    returns = known_returns(demos, float(cfg.agent.gamma), limit=PROBE_STATES)  # the same rows throughout

    def cal() -> dict[str, Any]:
        return {"calibration": calibration(net, demos, float(cfg.agent.gamma), returns=returns)}

    rows = [{"updates": 0, "loss": None, "init": fingerprint(net), **snapshot(net, pixels), **cal()}]
    losses: list[float] = []
    for step in range(1, updates + 1):
        losses.append(trainer.learner.update(trainer.stage.buffer.sample()))
        if step % every == 0 or step == updates:
            recent = losses[-every:]
            rows.append({"updates": step, "loss": sum(recent) / len(recent), **snapshot(net, pixels),
                         **cal()})
    return rows


def probe_weights(cfg: Any, run: Path, which: str, demos: str | None) -> dict[str, Any]:
    """A trained network of ``run`` (``which``: ``final`` or ``stage1``) on 256 demo states drawn
    with a generator seeded 0 from the run's prior knowledge (``demos``: another dataset)."""
    from memrl.checkpoint import load_qnet, load_stage1_qnet
    from memrl.data.demos import load_demos
    from memrl.modes import mode_of
    from memrl.train import prior_knowledge

    if demos is not None:
        td = load_demos(Path(demos), env_cfg=cfg.env)
    elif mode_of(cfg).needs_demos:
        td = prior_knowledge(cfg)
    else:
        raise ValueError("this run has no prior knowledge to draw the probe states from: give "
                         "demos=<a prior-knowledge dataset>")
    pick = torch.randperm(td.shape[0], generator=torch.Generator().manual_seed(0))[:PROBE_STATES]
    pixels = td["pixels"][pick]
    net = load_stage1_qnet(run) if which == "stage1" else load_qnet(run)[0]
    convs = [units for conv, units in dead_indices(net, pixels) if conv]
    return {"weights": which, **snapshot(net, pixels), "dead_conv_channels": convs,
            "calibration": calibration(net, td, float(cfg.agent.gamma))}


def line(row: dict[str, Any]) -> str:
    if "weights" in row:
        return (f"weights {row['weights']}  dead per ReLU {row['dead']}  dead channels of the conv "
                f"layers {row['dead_conv_channels']}  Q spread over states {row['q_spread']:.4f}  "
                f"greedy actions {row['greedy_actions']}\n{calibration_line(row['calibration'])}")
    loss = "-" if row["loss"] is None else f"{row['loss']:.4f}"
    init = f"  init {row['init']}" if "init" in row else ""
    cal = row["calibration"]
    bias = f"{cal['bias']:+.2f}" if cal["states"] else "-"
    return (f"updates {row['updates']:>6}  loss {loss:>7}  dead per ReLU {row['dead']}  "
            f"Q spread over states {row['q_spread']:.4f}  greedy actions {row['greedy_actions']}  "
            f"Q(s, a_demo) - return {bias}{init}")


def parse(argv: list[str]) -> dict[str, Any]:
    """The command line's options (``updates``, ``every``, ``weights``, ``demos``) and the
    config overrides (``overrides``); raises ValueError naming a bad value."""
    opts: dict[str, Any] = {"updates": 400, "every": 50, "weights": None, "demos": None, "overrides": []}
    for arg in argv:
        key, _, value = arg.partition("=")
        if key == "weights" and value not in ("final", "stage1"):
            raise ValueError(f"weights must be final or stage1, got {value!r}")
        if key in ("updates", "every") and (not value.isdigit() or int(value) < 1):
            raise ValueError(f"{key} must be a positive integer, got {value!r}")
        if key in ("weights", "demos"):
            opts[key] = value
        elif key in ("updates", "every"):
            opts[key] = int(value)
        else:
            opts["overrides"].append(arg)
    return opts


def run_config(file: Path, overrides: list[str]) -> Any:
    """The run's config with ``overrides`` (each must name a key the run has)."""
    from omegaconf import OmegaConf

    from memrl.errors import UserError, load_run_config

    if not file.is_file():
        raise UserError(f"{file}: no run config (expected a run folder or its config.yaml)")
    cfg = load_run_config(file)
    OmegaConf.set_struct(cfg, True)
    try:
        cfg.merge_with(OmegaConf.from_dotlist(overrides))
    except Exception as err:  # OmegaConf's key and value errors
        raise UserError(f"override: {str(err).splitlines()[0]}") from None
    OmegaConf.set_struct(cfg, False)
    cfg.progress = True  # no echo of the trainer's log lines
    return cfg


def main(argv: list[str]) -> int:
    from memrl.errors import UserError

    if not argv or "=" in argv[0]:
        print(USAGE, file=sys.stderr)
        return 2
    run = Path(argv[0])
    file = run / "config.yaml" if run.is_dir() else run
    try:
        opts = parse(argv[1:])
        cfg = run_config(file, opts["overrides"])
        if opts["weights"] is not None:
            print(line(probe_weights(cfg, file.parent, opts["weights"], opts["demos"])), flush=True)
            return 0
        with tempfile.TemporaryDirectory(prefix="stage1_probe_") as out:
            for row in probe(cfg, opts["updates"], opts["every"], Path(out)):
                print(line(row), flush=True)
    except (UserError, ValueError) as err:
        print(f"error: stage1_probe: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
