"""The learner, memory and e2e benchmarks run on tiny settings and report their figures; the
learner's speed options (channels_last, compile with its eager fallback) keep the numbers."""

from __future__ import annotations

import copy
import json
import os

import pytest
import torch

from memrl.bench import bench
from memrl.benchmarks import learner_speed
from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from tests.test_learner import batch


def test_bench_learner_times_memrl_beside_the_bare_loop(compose_cfg, tmp_path, monkeypatch):
    # the compile variant of the ablation stays eager here (compiling takes tens of seconds)
    monkeypatch.setattr("memrl.dqn.learner.compile_qnet", lambda qnet, sizes, device="cpu": False)
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)  # and so does the compiled update
    cfg = compose_cfg("bench", ["benchmarks=[learner]", "learner.batch_sizes=[4]",
                                "learner.seconds=0.01", "learner.rounds=1",
                                "learner.warmup_updates=1", "learner.buffer_transitions=40"])
    res = bench(cfg, tmp_path)["learner"]
    b4 = res["batch_4"]
    for name in ("bare_naive", "bare_tuned", "memrl_naive", "memrl_tuned",
                 "memrl_threads_2", "memrl_channels_last_false", "memrl_compile_true",
                 "memrl_precision_float32", "memrl_advantage_learning", "memrl_dueling",
                 "memrl_update_mode_compiled"):
        assert b4[name]["updates_per_s"] > 0 and len(b4[name]["rounds"]) == 1, name
    assert b4["memrl_update_mode_compiled"]["update_mode"] == "compiled"
    assert b4["memrl_tuned"]["update_mode"] == "eager"
    assert b4["bare_naive"]["threads"] == learner_speed.DEFAULT_THREADS
    assert b4["memrl_tuned"]["channels_last"] is True
    assert res["default_options"] == {"threads": 1, "channels_last": True, "compile": False,
                                      "pool_first": True, "precision": "auto"}
    assert b4["bare_naive"]["precision"] == "float32"
    assert b4["ratio_memrl_tuned_to_bare_tuned"] == pytest.approx(
        b4["memrl_tuned"]["updates_per_s"] / b4["bare_tuned"]["updates_per_s"], rel=1e-2)
    assert "load_average" in json.loads((tmp_path / "bench.json").read_text())["machine"]


def test_the_learner_bench_updates_with_the_advantage_learning_target():
    rb = learner_speed.fill_buffer(40, 4, seed=0)
    agent = learner_speed.default_agent_cfg()
    agent.batch_size, agent.precision = 4, "float32"
    plain = learner_speed.memrl_step(agent, rb, seed=0)()
    assert learner_speed.memrl_step(agent, rb, seed=0)() == plain  # seeded alike: the same update
    agent.advantage_learning = 0.9
    advantage = learner_speed.memrl_step(agent, rb, seed=0)()
    # the same weights and sample (seeded alike); the first target differs by alpha times the gap
    assert advantage != plain


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
    # 16 envs written one env step (16 rows) at a time, both storages timed in the same run
    streams = res["streams"]
    assert streams["compact"]["ring_frames"] == 2 * 3000 - 1 + 31 * 4
    assert streams["compact"]["env_steps"] == streams["naive"]["env_steps"] == 3000 // 16
    assert streams["ratio_compact_to_naive_bytes"] < 0.5
    assert streams["compact"]["step_us"] > 0 and streams["naive"]["step_us"] > 0
    # the same compact storage sampled with a crash share, timed beside it
    assert streams["crash"]["env_steps"] == streams["compact"]["env_steps"]
    assert streams["crash"]["ring_frames"] == streams["compact"]["ring_frames"]
    assert streams["ratio_crash_to_compact_sample_time"] == round(
        streams["crash"]["sample_us_per_step"] / streams["compact"]["sample_us_per_step"], 3)
    # and with prioritized replay (its priority writes timed with its samples)
    assert streams["priority"]["env_steps"] == streams["compact"]["env_steps"]
    assert streams["priority"]["ring_frames"] == streams["compact"]["ring_frames"]
    assert streams["ratio_priority_to_compact_sample_time"] == round(
        streams["priority"]["sample_us_per_step"] / streams["compact"]["sample_us_per_step"], 3)


def test_bench_e2e_reports_the_busy_share_after_warmup(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[e2e]", "e2e.total_frames=48",
                                "e2e.learner_seconds=0.05", "e2e.num_envs=[1,4]",
                                "e2e.overrides=['agent.warmup_frames=16','agent.batch_size=8',"
                                "'env.duration=20','buffer.capacity=200']"])
    out = bench(cfg, tmp_path)["e2e"]
    runs = out["runs"]
    assert out["device"] == "cpu" or torch.cuda.is_available()
    assert [(r["num_envs"], r["agent_options"]["overlap"]) for r in runs[:4]] == [
        (1, False), (1, True), (4, False), (4, True)]
    for res in runs:
        assert res["total_frames"] >= 48 and res["updates"] >= 2
        assert 0 < res["learner_busy_after_warmup"] <= 1
        assert res["updates_per_s_after_warmup"] > 0 and res["learner_only_updates_per_s"] > 0
    # The same seed and schedule: the same number of updates either way, at the replay ratio
    # of one env: a round every 4 env steps from the warm-up's 16 on.
    for a, b in ((runs[0], runs[1]), (runs[2], runs[3])):
        assert a["updates"] == b["updates"] == a["total_frames"] // 4 - 3


FLOAT32_UNIT_ROUNDOFF = 2.0 ** -24
"""u of float32: one rounding changes a value by at most u times its magnitude."""


def float32_bound(qnet, pixels: torch.Tensor) -> torch.Tensor:
    """First-order bound on |Q_float32 - Q_exact| of ``qnet`` for any summation order.

    Each conv or linear output z_l is a dot product of length K_l (+ bias); computed in float32
    in any order it is off by at most gamma_K (|W_l| |h_l-1| + |b_l|), gamma_K = K u / (1 - K u)
    (Higham, Accuracy and Stability of Numerical Algorithms, Sec. 3.1). Each such error reaches
    Q through the network's own Jacobian dQ/dz_l (ReLU and max-pool are piecewise linear), so
    |dQ| <= sum_l |dQ/dz_l| . bound_l, to first order in u. Exact values: float64.
    """
    net = copy.deepcopy(qnet).double()
    convs = [m for m in net.features if isinstance(m, torch.nn.Conv2d)]
    fcs = [m for m in net.head if isinstance(m, torch.nn.Linear)]
    h = pixels.reshape(-1, *pixels.shape[-3:]).double() / 255.0
    zs, local = [], []
    for layer in [*net.features, *net.head]:
        if isinstance(layer, torch.nn.Conv2d | torch.nn.Linear):
            k = (layer.in_channels * 9 if isinstance(layer, torch.nn.Conv2d) else layer.in_features)
            k += 1 + (layer is convs[0])  # the bias; the input's scaling by 1/255
            gamma = k * FLOAT32_UNIT_ROUNDOFF / (1 - k * FLOAT32_UNIT_ROUNDOFF)
            with torch.no_grad():
                w, bias = layer.weight.abs(), layer.bias.abs()
                size = (torch.nn.functional.conv2d(h.abs(), w, bias, padding=layer.padding)
                        if isinstance(layer, torch.nn.Conv2d)
                        else torch.nn.functional.linear(h.abs(), w, bias))
            h = layer(h)
            zs.append(h)
            local.append(gamma * size)
        else:
            h = layer(h)
    bound = torch.zeros_like(h)
    for action in range(h.shape[-1]):
        grads = torch.autograd.grad(h[:, action].sum(), zs, retain_graph=True)
        bound[:, action] = sum((g.abs() * r).flatten(1).sum(1) for g, r in zip(grads, local, strict=True))
    assert len(zs) == len(convs) + len(fcs)
    return bound.reshape(*pixels.shape[:-3], -1).float().detach()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_channels_last_learner_matches_the_default_layout(seed):
    """The layouts run different conv kernels (different summation orders): their Q-values and
    first loss differ by float32 rounding only, bounded from the dtype and the network's sums.
    float32 is pinned so that the bound holds on any x86 CPU, with or without native bf16."""
    torch.manual_seed(seed)
    a = Learner(AgentConfig(channels_last=False, lr=1e-3, precision="float32"))
    torch.manual_seed(seed)
    b = Learner(AgentConfig(channels_last=True, lr=1e-3, precision="float32"))
    assert b.qnet.features[0].weight.is_contiguous(memory_format=torch.channels_last)
    td = batch(seed=seed)
    q_a, q_b = a.q_values(td["pixels"]), b.q_values(td["pixels"])
    bound = float32_bound(a.qnet, td["pixels"])  # each layout is within it of the exact values
    assert ((q_a - q_b).abs() <= 2 * bound).all() and bool((bound > 0).all())
    # loss = mean 1/2 (Q(s, a) - y)^2, y = r + gamma Q_t(s', argmax Q(s', .)), target = online
    # weights at the first update: y moves by at most 3 x 2 next-state bounds (an argmax only
    # flips between actions within 2 bounds of each other); each item by |Q - y| e + e^2 / 2.
    gamma, act = a.cfg.gamma, td["action"].reshape(-1, 1)
    e_q = 2 * bound.gather(-1, act).squeeze(-1)
    e_y = gamma * 3 * 2 * float32_bound(a.qnet, td["next", "pixels"]).max(-1).values
    td_error = (q_a.gather(-1, act).squeeze(-1).abs() + td["next", "reward"].squeeze(-1).abs()
                + gamma * a.q_values(td["next", "pixels"]).abs().max(-1).values)
    e_loss = float((td_error * (e_q + e_y) + 0.5 * (e_q + e_y) ** 2).mean())
    loss_a, loss_b = a.update(td.clone()), b.update(td.clone())
    assert abs(loss_a - loss_b) <= e_loss + 8 * FLOAT32_UNIT_ROUNDOFF * loss_a  # + the mean's sum
    # Adam's first step moves each weight by at most lr (|m_hat| / sqrt(v_hat) <= 1), whatever
    # rounding did to a near-zero gradient: the two stay within 2 lr.
    for (k, x), y in zip(a.qnet.state_dict().items(), b.qnet.state_dict().values(), strict=True):
        assert ((x - y).abs() <= 2 * a.cfg.lr * (1 + FLOAT32_UNIT_ROUNDOFF) + 1e-7).all(), k


def test_compile_falls_back_to_eager_with_a_warning(monkeypatch):
    def broken(self, *args, **kwargs):
        raise RuntimeError("no C++ compiler")

    monkeypatch.setattr(torch.nn.Module, "compile", broken)
    with pytest.warns(RuntimeWarning, match="agent.compile"):
        learner = Learner(AgentConfig(compile=True, batch_size=4))
    assert not learner.compiled
    assert learner.update(batch()) >= 0


def test_bfloat16_conv_trunk_keeps_the_update_close_to_float32():
    """agent.precision=bfloat16 autocasts the convs only: Q-values and loss stay float32 and
    within bf16 rounding of the float32 network's."""
    torch.manual_seed(0)
    a = Learner(AgentConfig(precision="float32", lr=1e-3))
    torch.manual_seed(0)
    b = Learner(AgentConfig(precision="bfloat16", lr=1e-3))
    assert a.qnet.conv_dtype is None and b.qnet.conv_dtype is torch.bfloat16
    td = batch(seed=0)
    q_a, q_b = a.q_values(td["pixels"]), b.q_values(td["pixels"])
    assert q_b.dtype == torch.float32
    assert torch.allclose(q_a, q_b, rtol=0.05, atol=0.02) and not torch.equal(q_a, q_b)
    for seed in range(3):
        td = batch(seed=seed)
        assert b.update(td.clone()) == pytest.approx(a.update(td.clone()), rel=0.05, abs=1e-3)
    assert all(p.dtype == torch.float32 for p in b.qnet.parameters())
    # Gradients of one batch, same weights: the same direction within bf16 rounding.
    b.qnet.load_state_dict(a.qnet.state_dict())
    grads = []
    for learner in (a, b):
        learner.qnet.zero_grad()
        learner.loss(batch(seed=5)).backward()
        grads.append(torch.cat([p.grad.flatten() for p in learner.qnet.parameters()]))
    cosine = torch.nn.functional.cosine_similarity(grads[0], grads[1], dim=0)
    assert cosine > 0.99 and not torch.equal(grads[0], grads[1])


def test_unknown_precision_is_refused_naming_the_key(compose_cfg):
    from memrl.dqn.config import check_train_config
    from memrl.errors import ConfigError

    with pytest.raises(ConfigError, match="agent.precision"):
        check_train_config(compose_cfg("train", ["agent.precision=float16"]))


def test_bench_stage1_reports_each_variant(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", [
        "benchmarks=[stage1]", "stage1.updates=2", "stage1.check_every=1", "stage1.episodes=1",
        "stage1.drive_every=1", f"stage1.data_dir={tmp_path / 'data'}",
        "stage1.variants=[{name:plain,overrides:['env.duration=40','agent.batch_size=8','mode.example.episodes=3','env.bev.path_time=0']},"
        "{name:cue,overrides:['env.duration=40','agent.batch_size=8','env.bev.path_length=20','env.bev.path_time=0','mode.example.episodes=3']},"
        "{name:own,overrides:['env.duration=40','agent.batch_size=8'],demos:{episodes:2,"
        "tail_steps:3,driver:{merge_window:12.0},env:{initial_lane:non_goal,vehicles_count:0}}}]"])
    runs = bench(cfg, tmp_path)["stage1"]["runs"]
    assert [r["variant"] for r in runs] == ["plain", "cue", "own"]
    for r in runs:
        assert len(r["agreements"]) == 2 and r["survived_non_goal"] in (0, 1)
        assert r["both_non_goal"] <= min(r["survived_non_goal"], r["reached_non_goal"])
        # driven after update 1 and at the end; the last point is the run's own figures
        assert [c["updates"] for c in r["curve"]] == [1, 2]
        assert r["curve"][-1] == {"updates": 2, "survived": r["survived_non_goal"],
                                  "reached": r["reached_non_goal"], "both": r["both_non_goal"]}
        assert set(r["last_check_parts"]) == {"speed", "curvature", "steering_recall",
                                              "steering_share", "greedy_actions"}
    # its own recording: 2 stable episodes, each cut 3 steps after reaching the target lane
    assert runs[0]["demo_recipe"] == "example" and runs[2]["demo_recipe"]["tail_steps"] == 3
    assert runs[2]["demos"] < 2 * 40
    # The cue changes the env config, so its own example demos were recorded; "own" recorded
    # into its temporary folder.
    assert len(list((tmp_path / "data").rglob("metadata.json"))) == 2


def test_auto_precision_follows_the_cpu(monkeypatch):
    from memrl.dqn import learner as learner_mod

    monkeypatch.setattr(learner_mod, "native_bf16", lambda: False)
    assert learner_mod.conv_dtype("auto") is None
    monkeypatch.setattr(learner_mod, "native_bf16", lambda: True)
    assert learner_mod.conv_dtype("auto") is torch.bfloat16
    assert learner_mod.conv_dtype("float32") is None
    with pytest.raises(ValueError, match="agent.precision"):
        learner_mod.conv_dtype("float16")


def test_the_stacked_seeds_update_is_the_separate_updates():
    """K = 3 Table I networks stacked (vmap): each update's losses are the 3 separate updates'
    (float32: the sums' rounding, tests/test_update_modes.py's bound), and after 3 updates the
    weights within Adam's bound (each step moves a weight by at most lr)."""
    from memrl.benchmarks import seeds_speed
    from memrl.modules.qnet import QNetwork
    from tests.test_update_modes import RTOL

    torch.manual_seed(0)
    nets = [QNetwork() for _ in range(3)]
    data = seeds_speed._batches(3, 4, 0, torch.device("cpu"))
    sep_nets = copy.deepcopy(nets)
    sep = seeds_speed.separate(sep_nets, data, 2.5e-4, 0.95, 10.0)
    stk = seeds_speed.stacked(nets, data, 2.5e-4, 0.95, 10.0)
    for _ in range(3):
        a, b = sep(), stk()
        assert a.shape == (3,) and ((a - b).abs() <= RTOL * a.abs() + 1e-12).all()
    for k, net in enumerate(sep_nets):
        for name, w in net.state_dict().items():
            assert float((stk.params[name][k] - w).abs().max()) <= 3 * 2 * 2.5e-4, (k, name)


def test_bench_seeds_reports_both_updates_per_k(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[seeds]", "seeds.seeds=[1,2]", "seeds.batch_size=2",
                                "seeds.seconds=0.01", "seeds.rounds=1", "seeds.precision=float32"])
    res = bench(cfg, tmp_path)["seeds"]
    for k in (1, 2):
        row = res[f"k_{k}"]
        assert row["separate_updates_per_s"] > 0 and row["stacked_updates_per_s"] > 0
        assert row["first_loss_gap"] <= 1e-4 and len(row["separate"]) == 1


def test_bench_group_times_the_same_runs_in_one_process_and_in_k(compose_cfg, tmp_path):
    """Both arms train the same seeds on the same budget: the same env steps and updates, run by run."""
    overrides = ["+experiment=smoke", "agent.warmup_frames=20", "agent.batch_size=8", "buffer.capacity=400",
                 "env.duration=30", "env.num_envs=2", "logger=none", "progress=false", "eval.every=0"]
    cfg = compose_cfg("bench", ["benchmarks=[group]", "group.seeds=2", "group.frames=60", "group.rounds=1",
                                f"group.overrides=[{','.join(repr(o) for o in overrides)}]"])
    res = bench(cfg, tmp_path)["group"]
    many = res["rounds"]["processes"]
    for arm in ("one_process", "one_process_shared"):  # an engine per seed, one for both
        one = res["rounds"][arm]
        assert len(one) == len(many) == 1
        assert one[0]["frames"] == many[0]["frames"] >= 2 * 60 and one[0]["updates"] == many[0]["updates"] > 0
        ratio = one[0]["env_steps_per_s"] / many[0]["env_steps_per_s"]
        assert res[f"{arm}_over_processes"] == round(ratio, 3)
    assert res["one_process_threads"] == (os.cpu_count() or 1)  # 0: one per CPU, as a process alone
