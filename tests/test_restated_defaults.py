"""Defaults live in their schema only: no module reads a config key with a literal fallback
(``cfg.agent.get("lr", 1e-3)``) that could drift from the typed default (issue 29, item 4)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from memrl.dqn.config import AgentConfig, BufferConfig
from memrl.envs.config import LaneChangeConfig
from memrl.evaluation.periodic_config import PeriodicEvalConfig
from memrl.evaluation.protocol import ProtocolConfig
from memrl.modes import MODES, Stage1Config, Stage2Config
from memrl.modules.network_config import NetworkConfig

PACKAGE = Path(__file__).resolve().parents[1] / "memrl"
SCHEMAS = (AgentConfig, BufferConfig, *(m.schema for m in MODES.values()), Stage1Config, Stage2Config,
           LaneChangeConfig, NetworkConfig, PeriodicEvalConfig, ProtocolConfig)
KEYS = {f.name for schema in SCHEMAS for f in dataclasses.fields(schema)}

STORED_FILE_READERS = {
    "data/demos.py": "dataset metadata.json of earlier versions (frame_stack 4 before it was stored)",
    "data/minari_io.py": "Minari datasets' metadata, written by other tools",
    "envs/vector.py": "gymnasium's make_vec keyword API (a plain dict, not the composed config)",
    "evaluation/policies.py": "run folders' config.yaml (no config.yaml: a bare checkpoint)",
    "evaluation/figures.py": "run folders' config.yaml",
    "evaluation/session.py": "eval.json of earlier evaluations",
    "report.py": "eval.json of earlier evaluations",
}
"""Modules that read files written earlier or elsewhere, where a missing key has a meaning."""


def literal_fallbacks(source: str) -> list[str]:
    """``x.get("<schema key>", <literal>)`` calls in ``source``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr == "get" and len(node.args) == 2):
            continue
        key, fallback = node.args
        literal = isinstance(fallback, ast.Tuple | ast.List) or (
            isinstance(fallback, ast.Constant) and fallback.value is not None)
        if isinstance(key, ast.Constant) and key.value in KEYS and literal:
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


def test_the_scan_finds_a_restated_default():
    assert literal_fallbacks('n = cfg.agent.get("n_step", 1)\nm = cfg.get("n_step")') == [
        'line 1: cfg.agent.get(\'n_step\', 1)']


def test_no_module_restates_a_schema_default():
    offenders = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel not in STORED_FILE_READERS and (hits := literal_fallbacks(path.read_text())):
            offenders[rel] = hits
    assert offenders == {}


def test_every_listed_reader_exists():
    assert [rel for rel in STORED_FILE_READERS if not (PACKAGE / rel).is_file()] == []
