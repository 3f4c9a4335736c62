"""The README and the manual under docs/ are checked: every ``python -m memrl.<command>`` line
composes, every relative link and image resolves, and docs/configuration.md is what its
generator writes. Composes only (no run): a few seconds."""

from __future__ import annotations

import importlib.util
import re
import shlex
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser

from memrl.configs import register_configs
from memrl.schemas import SCHEMAS

ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = str(ROOT / "conf")

PENDING_PAGES: set[str] = set()
"""Pages the manual links to that other branches add. A link to one of them may dangle until
they are merged; the integrator empties this set after merging them (the pages are checked
like any other as soon as they exist)."""

PLACEHOLDERS = {
    "time": "2026-01-01_00-00-00", "run": "outputs/train/runs/2026-01-01_00-00-00",
    "run folder": "outputs/train/runs/2026-01-01_00-00-00",
    "older run": "outputs/train/runs/2025-12-31_00-00-00", "dir": "outputs/data/mine",
    "a": "outputs/study/a/runs", "b": "outputs/study/b/runs", "study": "outputs/study/cue",
    "dataset": "outputs/data/scripted/2026-01-01_00-00-00", "name": "ann",
    # docs/results/issue20: the recordings and the cand20k study's train overrides
    "recipe240_cue_s0": "outputs/data/recipe240_cue_s0",
    "recipe240_nocue_s0": "outputs/data/recipe240_nocue_s0",
    "cand20k overrides": '"+experiment=imitation","total_frames=20000","total_episodes=null"',
}
"""Values for the ``<...>`` placeholders of documented commands (a new placeholder needs one)."""

POSITIONAL = {"bench": "benchmarks"}
"""Commands that take bare words (``bench env`` -> ``benchmarks=[env]``, as ``memrl.cli``)."""

SKIP_FLAGS = {"-m", "--multirun", "--cfg", "job", "--help", "...", "\\"}


def doc_files() -> list[Path]:
    """README.md and every Markdown page under docs/ (results included)."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _fill(text: str) -> str:
    def sub(m: re.Match[str]) -> str:
        key = m.group(1)
        if key not in PLACEHOLDERS:
            raise KeyError(f"placeholder <{key}> has no value in tests/test_docs.py PLACEHOLDERS")
        return PLACEHOLDERS[key]

    return re.sub(r"<([a-z][a-z0-9_ ]*)>", sub, text)


def command_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, command) of every ``python -m memrl.*`` command in ``path``: in fenced
    blocks (joining ``\\`` continuations, dropping ``#`` comments) and in inline code."""
    lines = path.read_text().splitlines()
    found: list[tuple[int, str]] = []
    in_block, pending, start = False, "", 0
    for no, line in enumerate(lines, 1):
        if line.lstrip().startswith("```"):
            in_block, pending = not in_block, ""
            continue
        if in_block:
            text = pending + line
            if text.rstrip().endswith("\\"):
                pending, start = text.rstrip()[:-1] + " ", start or no
                continue
            pending = ""
            m = re.search(r"python -m memrl\.\S+.*", text)
            if m:
                found.append((start or no, m.group(0)))
            start = 0
    # inline code, possibly broken across the lines of one paragraph
    text = "\n".join(lines)
    for m in re.finditer(r"`(python -m memrl\.[^`]+)`", text):
        found.append((text.count("\n", 0, m.start()) + 1, " ".join(m.group(1).split())))
    return found


def _strip_comment(cmd: str) -> str:
    # a "#" that starts a shell comment: preceded by whitespace and outside quotes
    out, quote = [], None
    for i, ch in enumerate(cmd):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or cmd[i - 1].isspace()):
            break
        out.append(ch)
    return "".join(out).strip()


def parse(cmd: str) -> tuple[str, list[str]]:
    """(module, overrides) of one documented command."""
    from memrl.cli import normalize_argv

    tokens = shlex.split(_fill(_strip_comment(cmd)))
    module = tokens[2]
    words = [t for t in tokens[3:] if t not in SKIP_FLAGS]
    return module, normalize_argv(words, POSITIONAL.get(module.removeprefix("memrl.")))


def all_commands() -> list[tuple[str, int, str]]:
    """(page, line, command), each distinct command once (at its first place)."""
    seen: set[str] = set()
    out = []
    for p in doc_files():
        for no, cmd in command_lines(p):
            key = " ".join(_strip_comment(cmd).split())
            if key not in seen:
                seen.add(key)
                out.append((str(p.relative_to(ROOT)), no, cmd))
    return out


_COMPOSED: set[tuple[str, tuple[str, ...]]] = set()


def compose_once(command: str, overrides: list[str]):
    """Compose ``conf/<command>.yaml`` with ``overrides`` (each distinct pair once per session)."""
    key = (command, tuple(overrides))
    if key in _COMPOSED:
        return None
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=command, overrides=list(overrides),
                      return_hydra_config=any(o.lstrip("+~").startswith("hydra") for o in overrides))
    GlobalHydra.instance().clear()
    _COMPOSED.add(key)
    return cfg


COMMANDS = all_commands()


def test_docs_hold_commands():
    assert len([c for c in COMMANDS if c[0] == "README.md"]) >= 5


@pytest.mark.parametrize(("page", "line", "cmd"), COMMANDS,
                         ids=[f"{p}:{n}" for p, n, _ in COMMANDS])
def test_documented_command_composes(page, line, cmd):
    module, args = parse(cmd)
    command = module.removeprefix("memrl.")
    if command not in SCHEMAS:  # not a Hydra app: the module must exist
        assert importlib.util.find_spec(module) is not None, f"{page}:{line}: no module {module}"
        return
    parser = OverridesParser.create()
    jobs = BasicSweeper.split_arguments(parser.parse_overrides(args), None)
    register_configs()
    for batch in jobs:
        for overrides in batch:
            cfg = compose_once(command, list(overrides))
            if cfg is not None and command == "study":  # the train overrides it passes on compose too
                from omegaconf import OmegaConf

                study = cfg.study
                base = OmegaConf.to_container(study.train_overrides, resolve=False) or []
                extra = [list(base)]
                variants = OmegaConf.to_container(study.variants, resolve=False) if study.variants else {}
                extra += [list(base) + list(v) for v in variants.values()]
                from memrl.modes import by_label

                for train in extra:  # as the study composes each mode's cells: its own mode keys
                    for mode in study.modes:
                        spec = by_label(str(mode))
                        compose_once("train", [*spec.own_overrides([str(o) for o in train]),
                                               *spec.overrides])


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|<img[^>]*\ssrc=\"([^\"]+)\"")


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of the headings of a Markdown page."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    out = set()
    for m in re.finditer(r"^#+\s+(.+?)\s*$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
        out.add(slug)
    return out


def test_relative_links_resolve():
    """Every relative link and image of README and docs/ names a file that exists (or a pending
    page), and a ``#fragment`` names a heading of its page."""
    missing = []
    for page in doc_files():
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # not inside code blocks
        for m in LINK.finditer(text):
            link = m.group(1) or m.group(2)
            target, _, fragment = link.partition("#")
            if re.match(r"[a-z]+:", target):
                continue
            path = (page.parent / target).resolve() if target else page
            rel = path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path)
            if not path.exists():
                if rel not in PENDING_PAGES:
                    missing.append(f"{page.relative_to(ROOT)}: {link}")
            elif fragment and path.suffix == ".md" and fragment not in anchors(path):
                missing.append(f"{page.relative_to(ROOT)}: {link} (no such heading)")
    assert not missing, "links that resolve to nothing:\n" + "\n".join(missing)


def test_configuration_reference_is_generated():
    from memrl.config_reference import markdown
    from memrl.configs import register_configs

    register_configs()
    assert (ROOT / "docs" / "configuration.md").read_text() == markdown(), (
        "docs/configuration.md is stale: python -m memrl.configs --markdown > docs/configuration.md")


def test_configuration_reference_gives_each_key_its_own_comment(tmp_path):
    """Keys of one name under two groups keep their own comments (the dotted path by
    indentation); a full-line comment above a key is its comment; nested keys and list lines."""
    from memrl.config_reference import _comments_of

    yaml = tmp_path / "c.yaml"
    yaml.write_text("learner:   # the learner\n  rounds: 3   # interleaved rounds\n  sizes:\n    - 1\n"
                    "group:\n  # the arms alternate\n  rounds: 2\n  inner:\n    rounds: 1  # deepest\n"
                    "top: 1\n")
    assert _comments_of(yaml) == {"learner": "the learner", "learner.rounds": "interleaved rounds",
                                  "group.rounds": "the arms alternate", "group.inner.rounds": "deepest"}


def code_block_after(page: str, marker: str) -> str:
    """The fenced code block right after ``<!-- test:<marker> -->`` in ``page``."""
    text = (ROOT / page).read_text()
    m = re.search(rf"<!-- test:{marker} -->\s*```\w*\n(.*?)```", text, flags=re.S)
    assert m, f"{page}: no block after <!-- test:{marker} -->"
    return m.group(1)


def test_sb3_example_runs():
    """The Stable-Baselines3 example of docs/environments.md trains and acts (SB3 is optional)."""
    pytest.importorskip("stable_baselines3")
    code = code_block_after("docs/environments.md", "sb3")
    exec(compile(code, "docs/environments.md:sb3", "exec"), {"__name__": "sb3_example"})
