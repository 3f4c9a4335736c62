"""A person's evaluation over several sittings, stopped with Esc, and how the report counts it."""

from __future__ import annotations

import json

import pytest

from memrl.evaluate import evaluate
from memrl.evaluation.results import read_result
from memrl.modules.human import KeyboardDriver
from memrl.stop import Stopped

SMALL = ["protocol.episodes=2", "protocol.duration=12", "workers=1", "batch=1", "progress=false",
         "policy=human", "policy.person=ann", "policy.driver.fps=0", "policy.driver.wait_for_start=false"]


@pytest.fixture
def pg(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import pygame

    pygame.display.init()
    pygame.event.clear()
    yield pygame
    pygame.display.quit()


def esc_at_step(monkeypatch, pg, n: int) -> None:
    """Esc arrives before the ``n``-th action of the sitting (counted from 1)."""
    real = KeyboardDriver.act
    calls = {"n": 0}

    def act(self, env, pixels):
        calls["n"] += 1
        if calls["n"] == n:
            pg.event.post(pg.event.Event(pg.KEYDOWN, key=pg.K_ESCAPE))
        return real(self, env, pixels)

    monkeypatch.setattr(KeyboardDriver, "act", act)


def test_esc_before_any_episode_is_one_line_and_exit_130(pg, compose_cfg, tmp_path, monkeypatch):
    esc_at_step(monkeypatch, pg, 3)
    with pytest.raises(Stopped, match="^stopped before any episode finished; nothing saved$") as stop:
        evaluate(compose_cfg("evaluate", SMALL), out_dir=tmp_path / "ev")
    assert stop.value.status == 130 and not (tmp_path / "ev" / "eval.json").exists()


def test_two_sittings_equal_one_and_the_report_counts_only_complete(pg, compose_cfg, tmp_path,
                                                                    monkeypatch):
    whole = evaluate(compose_cfg("evaluate", SMALL), out_dir=tmp_path / "whole")[0]
    with monkeypatch.context() as m:
        esc_at_step(m, pg, 12 + 12 + 5)  # during the third of four episodes
        with pytest.raises(Stopped) as stop:
            evaluate(compose_cfg("evaluate", SMALL), out_dir=tmp_path / "part")
    part = tmp_path / "part"
    assert str(stop.value) == (f"stopped after 2 of 4 episodes, saved in {part}; go on with: "
                               f"python -m memrl.evaluate policy=human policy.person=ann resume={part}")
    first = read_result(part)
    assert first.stopped_early and first.meta["person"] == "ann" and len(first.records()) == 2
    # the report leaves the partial one out of the table and lists it
    from memrl.report import report

    (tmp_path / "runs").mkdir()
    rep = report(compose_cfg("report", [f"runs=[{part},{tmp_path / 'whole'}]", "fig5=false"]),
                 out_dir=tmp_path / "rep")
    doc = json.loads(rep.report_json.read_text())
    assert doc["sources"] == [str(whole.path.resolve())]
    assert doc["partial"][0]["episodes"] == 2 and doc["partial"][0]["planned"] == 4
    assert "2 of 4 (partial)" in rep.table_md.read_text()
    # a different person cannot go on with ann's evaluation
    with pytest.raises(Exception, match="not human \\[bob\\]"):
        evaluate(compose_cfg("evaluate", [*SMALL, "policy.person=bob", f"resume={part}"]))
    # the second sitting drives the missing scenes only; the folder equals one sitting's
    done = evaluate(compose_cfg("evaluate", [*SMALL, f"resume={part}"]))[0]
    assert done.path == part and not done.stopped_early
    assert [r.row() for r in done.records()] == [r.row() for r in whole.records()]
    with pytest.raises(Exception, match="is complete"):
        evaluate(compose_cfg("evaluate", [*SMALL, f"resume={part}"]))
