"""The learner, memory and e2e benchmarks run on tiny settings and report their figures; the
learner's speed options (channels_last, compile with its eager fallback) keep the numbers."""

from __future__ import annotations

import json

import pytest
import torch

from memrl.bench import bench
from memrl.benchmarks import learner_speed
from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from tests.test_learner import batch


def test_bench_learner_times_memrl_beside_the_bare_loop(compose_cfg, tmp_path, monkeypatch):
    # the compile variant of the ablation stays eager here (compiling takes tens of seconds)
    monkeypatch.setattr("memrl.dqn.learner.compile_qnet", lambda qnet, sizes: False)
    cfg = compose_cfg("bench", ["benchmarks=[learner]", "learner.batch_sizes=[4]",
                                "learner.seconds=0.01", "learner.rounds=1",
                                "learner.warmup_updates=1", "learner.buffer_transitions=40"])
    res = bench(cfg, tmp_path)["learner"]
    b4 = res["batch_4"]
    for name in ("bare_naive", "bare_tuned", "memrl_naive", "memrl_tuned",
                 "memrl_threads_2", "memrl_channels_last_false", "memrl_compile_true"):
        assert b4[name]["updates_per_s"] > 0 and len(b4[name]["rounds"]) == 1, name
    assert b4["bare_naive"]["threads"] == learner_speed.DEFAULT_THREADS
    assert b4["memrl_tuned"]["channels_last"] is True
    assert res["default_options"] == {"threads": 1, "channels_last": True, "compile": False,
                                      "pool_first": True}
    assert b4["ratio_memrl_tuned_to_bare_tuned"] == pytest.approx(
        b4["memrl_tuned"]["updates_per_s"] / b4["bare_tuned"]["updates_per_s"], rel=1e-2)
    assert "load_average" in json.loads((tmp_path / "bench.json").read_text())["machine"]


def test_default_agent_cfg_is_the_training_agent_config(compose_cfg):
    train = compose_cfg("train")
    assert learner_speed.default_agent_cfg() == train.agent


def test_bench_memory_measures_both_storages_in_fresh_processes(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[memory]", "memory.transitions=3000"])
    res = bench(cfg, tmp_path)["memory"]
    compact, naive = res["compact"], res["naive"]
    assert compact["transitions"] == naive["transitions"] == 3000
    assert compact["ring_frames"] == 2 * 3000 + 3
    # the ring is touched at its first write: the compact buffer is resident at once
    assert compact["added_bytes"] >= 0.7 * compact["storage_bytes"]
    assert naive["added_bytes"] > 2 * compact["added_bytes"]
    assert res["ratio_compact_to_naive"] < 0.5 and res["compact_within_limit"]


def test_bench_e2e_reports_the_busy_share_after_warmup(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[e2e]", "e2e.total_frames=48",
                                "e2e.learner_seconds=0.05",
                                "e2e.overrides=['agent.warmup_frames=16','agent.batch_size=8',"
                                "'env.duration=20','buffer.capacity=200']"])
    runs = bench(cfg, tmp_path)["e2e"]["runs"]
    assert [r["agent_options"]["overlap"] for r in runs] == [False, True]
    for res in runs:
        assert res["total_frames"] >= 48 and res["updates"] >= 2
        assert 0 < res["learner_busy_after_warmup"] <= 1
        assert res["updates_per_s_after_warmup"] > 0 and res["learner_only_updates_per_s"] > 0
    # The same seed and schedule: the same number of updates either way.
    assert runs[0]["updates"] == runs[1]["updates"]


def test_channels_last_learner_matches_the_default_layout():
    torch.manual_seed(0)
    a = Learner(AgentConfig(channels_last=False, lr=1e-3))
    torch.manual_seed(0)
    b = Learner(AgentConfig(channels_last=True, lr=1e-3))
    conv = b.qnet.features[0].weight
    assert conv.is_contiguous(memory_format=torch.channels_last)
    for seed in range(3):
        td = batch(seed=seed)
        assert a.update(td.clone()) == pytest.approx(b.update(td.clone()), rel=1e-4, abs=1e-6)
    for (k, x), y in zip(a.qnet.state_dict().items(), b.qnet.state_dict().values(), strict=True):
        assert torch.allclose(x, y, rtol=1e-4, atol=1e-6), k


def test_compile_falls_back_to_eager_with_a_warning(monkeypatch):
    def broken(self, *args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(torch.nn.Module, "compile", broken)
    with pytest.warns(RuntimeWarning, match="agent.compile"):
        learner = Learner(AgentConfig(compile=True, batch_size=4))
    assert not learner.compiled
    assert learner.update(batch()) >= 0
