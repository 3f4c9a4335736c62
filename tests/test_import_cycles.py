"""No import cycles, and every import goes down the layers.

No cycle: between memrl's packages, and between any two of its modules. Every ``import``
counts, also those inside functions (a lazy import is still a dependency); only ``if
TYPE_CHECKING:`` blocks are left out (they never run).

The layers, bottom to top (:data:`LAYERS`); a module imports from its own layer or from lower
ones, never from a higher one:

1. base: errors, fields, known keys, progress bars, CSV tables, loggers, run folders and their
   lock, stopping (:mod:`memrl.stop`), worker processes; the ``memrl`` package itself.
2. ``memrl.envs``: the simulator, its renderer, the TorchRL pipeline, the batched engine. The
   controllers of other cars are made through a registry that higher layers fill
   (:func:`memrl.envs.controllers.register_controller`).
3. ``memrl.modules``: networks and policies.
4. ``memrl.data``, ``memrl.control``: datasets, replay buffers and recording; the deployment's
   classical controllers.
5. ``memrl.modes``, ``memrl.losses``, ``memrl.values``: what each training mode is, the loss
   terms its stages list, and the view of the Q-functions the terms see.
6. ``memrl.checkpoint``: every file a run writes to be read again (weights, Q-networks,
   policies, resume state, manifests, their error) and the cars driven by past runs.
7. ``memrl.evaluation``: the protocol, its runners, results, statistics and figures.
8. ``memrl.dqn``, ``memrl.imitation``, ``memrl.provenance``: the trainers (a run's periodic
   evaluation and mode B's drive checks use the evaluation).
9. command plumbing: ``memrl.schemas``, ``memrl.configs``, ``memrl.config_reference``,
   ``memrl.hydra_callbacks``, ``memrl.cli``.
10. the commands (``python -m memrl.<command>``) and what drives them: studies, benchmarks,
    tools.

A string that names a memrl module to import (``importlib.import_module("memrl...")``, an
entry point ``"memrl.x.y:Name"``) is a dependency too, and goes down the layers as well; only
:data:`DYNAMIC_IMPORTS` import a module named at run time (a user's code).
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "memrl"
PACKAGES = ("envs", "modules", "data", "control", "checkpoint", "evaluation", "dqn", "imitation", "studies")

LAYERS: tuple[tuple[str, ...], ...] = (
    ("memrl", "memrl.errors", "memrl.fields", "memrl.known_keys", "memrl.progress", "memrl.csv_table",
     "memrl.loggers", "memrl.run_lock", "memrl.run_folder", "memrl.stop", "memrl.workers"),
    ("memrl.envs",),
    ("memrl.modules",),
    ("memrl.data", "memrl.control"),
    ("memrl.modes", "memrl.losses", "memrl.values"),
    ("memrl.checkpoint",),
    ("memrl.evaluation",),
    ("memrl.dqn", "memrl.imitation", "memrl.provenance"),
    ("memrl.schemas", "memrl.configs", "memrl.config_reference", "memrl.hydra_callbacks", "memrl.cli"),
    ("memrl.train", "memrl.evaluate", "memrl.record", "memrl.preview", "memrl.deploy", "memrl.dagger",
     "memrl.report", "memrl.study", "memrl.bench", "memrl.studies", "memrl.benchmarks", "memrl.tools"),
)
"""memrl's layers, bottom to top: module names and package names (a package holds its modules)."""

DYNAMIC_IMPORTS = {"memrl.evaluation.external": "policy=python imports the user's module:attr target"}
"""Modules that import a module named at run time, and why."""

ENTRY_POINT = re.compile(r"memrl(\.\w+)+:\w+")
"""A string naming an attribute of a memrl module to import (gymnasium's entry points)."""


def _module_name(path: Path) -> str:
    return ".".join(("memrl", *path.relative_to(ROOT).with_suffix("").parts)).removesuffix(".__init__")


def _imports(tree: ast.AST) -> list[str]:
    """Modules named by the imports of ``tree``, outside ``if TYPE_CHECKING:`` blocks."""
    out: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            out.extend(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.extend(a.name for a in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return out


def _string_imports(tree: ast.AST) -> tuple[list[str], bool]:
    """Modules that ``tree`` names in strings to import (``import_module("memrl.x")``,
    ``__import__("memrl.x")``, ``"memrl.x:Name"``), and whether it imports a module whose name
    is no literal (one named at run time)."""
    named: list[str] = []
    dynamic = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if name in ("import_module", "__import__") and node.args:
                arg = node.args[0]
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    named.append(arg.value)
                else:
                    dynamic = True
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and ENTRY_POINT.fullmatch(node.value):
            named.append(node.value.split(":", 1)[0])
    return named, dynamic


def _parse(files: dict[str, Path]) -> dict[str, ast.AST]:
    return {name: ast.parse(path.read_text()) for name, path in files.items()}


def _files() -> dict[str, Path]:
    return {_module_name(p): p for p in ROOT.rglob("*.py")}


def import_graph(trees: dict[str, ast.AST] | None = None, strings: bool = False) -> dict[str, set[str]]:
    """memrl module -> the memrl modules it imports (``strings``: also those it names in
    strings to import)."""
    trees = _parse(_files()) if trees is None else trees
    known = set(trees)
    out = {}
    for name, tree in trees.items():
        named = _imports(tree) + (_string_imports(tree)[0] if strings else [])
        out[name] = {m for m in named if m in known and m != name}
    return out


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of the longest name there that is ``module`` or a package above it."""
    best = max(((len(p), i) for i, names in enumerate(LAYERS) for p in names
                if module == p or module.startswith(p + ".")), default=None)
    if best is None:
        raise KeyError(f"{module}: in no layer of tests/test_import_cycles.py LAYERS (add it to one)")
    return best[1]


def upward(graph: dict[str, set[str]]) -> list[str]:
    """The imports of ``graph`` that go from a lower layer to a higher one."""
    return [f"{m} (layer {layer_of(m) + 1}) imports {d} (layer {layer_of(d) + 1})"
            for m, deps in sorted(graph.items()) for d in sorted(deps) if layer_of(d) > layer_of(m)]


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def test_no_module_imports_itself_through_others():
    assert cycles(import_graph()) == []


def test_the_packages_form_no_cycle():
    packages: dict[str, set[str]] = defaultdict(set)
    for name, deps in import_graph().items():
        parts = name.split(".")
        if len(parts) > 2 and parts[1] in PACKAGES:
            packages[parts[1]] |= {d.split(".")[1] for d in deps
                                   if len(d.split(".")) > 2 and d.split(".")[1] in PACKAGES} - {parts[1]}
    assert cycles(dict(packages)) == []


def test_the_checker_sees_a_lazy_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import memrl.x\n"
                     "def f():\n    from memrl.y import z\n")
    assert _imports(tree) == ["typing", "typing.TYPE_CHECKING", "memrl.y", "memrl.y.z"]


def test_every_module_has_a_layer():
    for name in _files():
        layer_of(name)  # raises naming a module in no layer


def test_every_import_goes_down_the_layers():
    """Lazy imports and string-named ones included."""
    assert upward(import_graph(strings=True)) == []


def test_only_user_code_is_imported_by_a_name_known_at_run_time():
    dynamic = sorted(name for name, tree in _parse(_files()).items() if _string_imports(tree)[1])
    assert dynamic == sorted(DYNAMIC_IMPORTS)


def test_the_checker_sees_a_planted_upward_import():
    trees = _parse(_files())
    assert upward(import_graph(trees, strings=True)) == []
    planted = {  # an env module that imports the trainer, lazily, and one that names the pool by a string
        "memrl.envs.controllers": "def make():\n    from memrl.dqn.loop import Trainer\n",
        "memrl.envs.scene": "import importlib\nLEARNED = 'memrl.checkpoint.opponents:LearnedCarController'\n",
        "memrl.modes": "def f():\n    return __import__('memrl.dqn.learner')\n",
    }
    trees_planted = {**trees, **{m: ast.parse(code) for m, code in planted.items()}}
    found = upward(import_graph(trees_planted, strings=True))
    assert found == ["memrl.envs.controllers (layer 2) imports memrl.dqn.loop (layer 8)",
                     "memrl.envs.scene (layer 2) imports memrl.checkpoint.opponents (layer 6)",
                     "memrl.modes (layer 5) imports memrl.dqn.learner (layer 8)"]
    graph = import_graph(trees)
    graph["memrl.modules.qnet"].add("memrl.checkpoint")  # one extra edge in the real graph
    assert upward(graph) == ["memrl.modules.qnet (layer 3) imports memrl.checkpoint (layer 6)"]
    assert _string_imports(ast.parse("import importlib\nimportlib.import_module(name)\n")) == ([], True)
