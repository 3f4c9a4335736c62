"""The composed configs hold the values their YAML files (and the README) document, and the
command line answers ``--help`` without loading torch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
COMMANDS = ("train", "record", "evaluate", "report", "deploy", "bench", "preview", "study", "dagger")
GROUP_FILES = {("train", "env"): "env/lane_change.yaml", ("train", "agent"): "agent/dqn.yaml",
               ("train", "buffer"): "buffer/default.yaml", ("deploy", "deploy"): "deploy/default.yaml",
               ("evaluate", "protocol"): "protocol/paper.yaml"}


def documented(path: Path) -> dict:
    """The literal values of a YAML config file (no defaults list, no interpolations)."""
    values = yaml.safe_load(path.read_text()) or {}
    values.pop("defaults", None)
    return values


def assert_holds(composed, values: dict, prefix: str = "") -> None:
    for key, value in values.items():
        if isinstance(value, str) and "${" in value:
            continue  # an interpolation: resolved at run time
        if isinstance(value, dict):
            assert_holds(composed[key], value, f"{prefix}{key}.")
            continue
        have = composed[key]
        have = OmegaConf.to_container(have) if OmegaConf.is_config(have) else have
        assert have == value, f"{prefix}{key}: composed {have!r}, documented {value!r}"


@pytest.mark.parametrize("command", COMMANDS)
def test_composed_config_holds_its_documented_values(compose_cfg, command):
    cfg = compose_cfg(command)
    assert_holds(cfg, documented(CONF / f"{command}.yaml"))
    for (cmd, key), file in GROUP_FILES.items():
        if cmd == command:
            own = documented(CONF / f"{command}.yaml").get(key, {})
            group = {k: v for k, v in documented(CONF / file).items() if k not in own}
            assert_holds(cfg[key], group, f"{key}.")


@pytest.mark.parametrize("experiment", [None, "paper"])
def test_periodic_evaluation_is_on_by_default(compose_cfg, experiment):
    """conf/train.yaml and the README say eval.every=100; the typed node must not undo it."""
    cfg = compose_cfg("train", [f"+experiment={experiment}"] if experiment else [])
    assert cfg.eval.every == 100 and cfg.eval.episodes == 10
    assert cfg.mode.name == "default"


def test_presets_win_over_the_defaults(compose_cfg):
    assert compose_cfg("train", ["+experiment=smoke"]).eval.every == 0
    paper = compose_cfg("train", ["+experiment=paper", "+mode=B"])
    assert paper.total_episodes == 100000 and paper.mode.name == "B"
    assert paper.agent.eps_decay_frames == 1000000
    assert paper.mode.stage1.margin_weight == 0 and paper.mode.stage1.lr is None
    assert paper.env.bev.path_length == 0
    # the paper's B: stage 2 trains as Default; the paper's A: eq. (1) alone
    assert paper.mode.stage2.demo_fraction == paper.mode.stage2.margin_weight == 0
    assert compose_cfg("train", ["+mode=A", "+experiment=paper"]).mode.margin_weight == 0
    ours = compose_cfg("train", ["+mode=B"]).mode
    assert (ours.stage2.demo_fraction, ours.stage2.margin_weight) == (0.1, 3.0)
    assert compose_cfg("train", ["+mode=A"]).mode.margin_weight == 3.0
    from memrl.data.recipe import LEGACY_RECIPE, recipe_values

    # whole noiseless episodes in the training env's own episodes, not the manoeuvre recipe
    assert recipe_values(paper.mode.example) == recipe_values(LEGACY_RECIPE)
    assert recipe_values(compose_cfg("train", ["+mode=B"]).mode.example)["action_noise"] == 0.2


def command(args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    return subprocess.run([sys.executable, "-X", "importtime", "-m", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("name", ["train", "evaluate", "study"])
def test_help_lists_groups_and_config_without_importing_torch(name):
    proc = command([f"memrl.{name}", "--help"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "== Configuration groups ==" in proc.stdout and "env: lane_change" in proc.stdout
    if name == "train":
        assert "mode: A, B" in proc.stdout and "eval:\n  every: 100" in proc.stdout
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines()
                if line.startswith("import time:")}
    assert "json" in imported  # the import log is there
    assert not {"torch", "tensordict", "torchrl", "highway_env"} & imported


def test_tab_completion_answers_without_importing_torch():
    # Hydra's bash completion asks the script itself with the line typed so far
    env_line = {"COMP_LINE": "python memrl/train.py mo", "COMP_POINT": "25"}
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "memrl.train",
                           "-sc", "query=bash"], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, **env_line}, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "mode=" in proc.stdout.split()
    imported = {line.split("|")[-1].strip() for line in proc.stderr.splitlines()
                if line.startswith("import time:")}
    assert "torch" not in imported


def _leaves(node, prefix=""):
    for key, value in node.items():
        if isinstance(value, dict):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


@pytest.mark.parametrize(("path", "schema"), [
    ("agent/dqn.yaml", "memrl.dqn.config:AgentConfig"),
    ("buffer/default.yaml", "memrl.dqn.config:BufferConfig"),
    ("deploy/default.yaml", "memrl.control.config:DeployConfig"),
    ("env/lane_change.yaml", "memrl.envs.config:LaneChangeConfig"),
])
def test_group_files_hold_only_what_differs_from_their_schema(path, schema):
    """Defaults live in one place, the dataclass schema: a group file that repeats a default
    would silently win over a later change of the schema."""
    import importlib


    module, name = schema.split(":")
    defaults = OmegaConf.to_container(OmegaConf.structured(getattr(importlib.import_module(module), name)))
    raw = yaml.safe_load((CONF / path).read_text()) or {}
    raw.pop("defaults", None)
    repeated = []
    for key, value in _leaves(raw):
        cur = defaults
        for part in key.split("."):
            cur = cur.get(part, "<missing>") if isinstance(cur, dict) else "<missing>"
        if cur == value:
            repeated.append(key)
    assert not repeated, f"conf/{path} repeats the schema's defaults of {repeated}"


@pytest.mark.parametrize("mode", ["A", "B"])
def test_mode_files_comment_the_composed_defaults(compose_cfg, mode):
    """``conf/mode/<mode>.yaml`` lists its keys in comments (``#   key: value  doc``): each listed
    value is the composed default, so the comments cannot drift from the dataclasses."""
    import re

    cfg = compose_cfg("train", [f"+mode={mode}"])
    listed = re.findall(r"^#   ([a-z_.0-9]+): (\S+)", (CONF / "mode" / f"{mode}.yaml").read_text(),
                        flags=re.M)
    assert len(listed) >= (5 if mode == "A" else 15)
    for key, text in listed:
        have = OmegaConf.select(cfg.mode, key)
        assert have == yaml.safe_load(text), f"mode.{key}: composed {have!r}, commented {text}"
