"""Exploration options: what each one draws, batched over envs, and exact resume."""

from __future__ import annotations

import csv

import pytest
import torch
from tensordict import TensorDict

from memrl.dqn.exploration import KEEP_CURVATURE, make_exploration
from memrl.envs.vehicles import ACTIONS, IDLE
from memrl.train import train
from tests.helpers import TINY


def td(n, step_count=None, q=None):
    data = {"action": torch.full((n,), IDLE)}
    if step_count is not None:
        data["step_count"] = torch.as_tensor(step_count).reshape(n, 1)
    if q is not None:
        data["action_value"] = q
    return TensorDict(data, [n])


def test_keep_curvature_actions_change_only_the_speed():
    assert [ACTIONS[i] for i in KEEP_CURVATURE.tolist()] == [(-1, 0), (0, 0), (1, 0)]


def test_speed_only_random_actions_keep_the_curvature():
    torch.manual_seed(0)
    explore = make_exploration(1.0, 1.0, 10, kind="speed_only")
    actions = torch.cat([explore(td(64))["action"] for _ in range(20)])
    assert set(actions.tolist()) == set(KEEP_CURVATURE.tolist())


def test_ez_greedy_repeats_each_random_action_for_its_drawn_duration():
    torch.manual_seed(0)
    n = 8
    explore = make_exploration(1.0, 1.0, 10, kind="ez_greedy", num_envs=n, ez_max_duration=5)
    steps = []
    for t in range(40):
        before = explore.remaining.clone()
        action = explore(td(n, step_count=torch.full((n,), t + 1)))["action"]
        steps.append((before, explore.repeat.clone(), action))
    for before, repeat, action in steps:
        # an env mid-repeat plays its repeated action; with eps = 1 every env always is
        assert torch.equal(action, repeat)
        assert bool((before <= 4).all())  # at most max_duration - 1 left after a start
    # runs of one action are at most 5 long unless the next draw repeats it by chance
    lengths = torch.stack([b for b, _, _ in steps])
    assert int(lengths.max()) == 4


def test_ez_greedy_at_epsilon_zero_is_greedy_and_a_new_episode_ends_a_repeat():
    explore = make_exploration(1.0, 0.0, 1, kind="ez_greedy", num_envs=2)
    explore.remaining.fill_(3)
    explore.repeat.fill_(0)
    explore.step(1)  # epsilon 0
    out = explore(td(2, step_count=torch.tensor([0, 5])))["action"]
    assert out.tolist() == [IDLE, 0]  # env 0 started a new episode: its repeat ended
    assert explore.remaining.tolist() == [0, 2]


def test_boltzmann_follows_the_q_values_as_the_temperature_falls():
    torch.manual_seed(0)
    q = torch.zeros(4000, 9)
    q[:, 2] = 1.0
    hot = make_exploration(1.0, 1.0, 10, kind="boltzmann", temperature_start=100.0,
                           temperature_end=100.0)
    cold = make_exploration(1.0, 1.0, 10, kind="boltzmann", temperature_start=1e-3,
                            temperature_end=1e-3)
    assert set(cold(td(4000, q=q))["action"].tolist()) == {2}
    counts = torch.bincount(hot(td(4000, q=q))["action"], minlength=9)
    # near-uniform: each action ~444 of 4000; 5 sigma is ~110
    assert int(counts.min()) > 300 and int(counts.max()) < 600


def test_epsilon_anneals_by_frames_in_one_step():
    explore = make_exploration(1.0, 0.1, 100)
    explore.step(16)
    assert float(explore.eps) == pytest.approx(1.0 - 16 * 0.9 / 100, abs=1e-6)
    explore.step(1000)
    assert float(explore.eps) == pytest.approx(0.1)


def test_an_unknown_exploration_names_the_key(compose_cfg, tmp_path):
    from memrl.errors import ConfigError

    cfg = compose_cfg("train", TINY + ["agent.exploration=noisy"])
    with pytest.raises(ConfigError, match=r"agent\.exploration"):
        train(cfg, tmp_path)


@pytest.mark.parametrize("kind", ["ez_greedy", "ez_speed", "boltzmann", "speed_only"])
def test_each_option_trains_and_the_repeats_resume_exactly(compose_cfg, tmp_path, kind):
    extra = ["env.num_envs=4", "total_episodes=8", "checkpoint_every=3", f"agent.exploration={kind}"]
    full = train(compose_cfg("train", TINY + extra), tmp_path / "full")
    assert full.episodes >= 8 and full.updates > 0
    if kind not in ("ez_greedy", "ez_speed"):
        return
    short = train(compose_cfg("train", TINY + extra[:1] + ["total_episodes=4"] + extra[2:]),
                  tmp_path / "cut")
    assert short.episodes < full.episodes
    resumed = train(compose_cfg("train", TINY + extra + [f"resume={tmp_path / 'cut'}"]))
    assert resumed.frames == full.frames

    def rows(run):
        with (tmp_path / run / "episodes.csv").open() as f:
            return list(csv.DictReader(f))

    assert rows("cut") == rows("full")


def test_ez_speed_holds_one_speed_change_and_takes_the_curvature_change_from_the_greedy_action():
    torch.manual_seed(0)
    n = 6
    explore = make_exploration(1.0, 1.0, 10, kind="ez_speed", num_envs=n, ez_max_duration=4)
    held, starts = [], 0
    for t in range(60):
        greedy = torch.randint(9, (n,))  # a different greedy action at every step
        before = explore.remaining.clone()
        action = explore(TensorDict({"action": greedy.clone(),
                                     "step_count": torch.full((n, 1), t + 1)}, [n]))["action"]
        starts += int((before == 0).sum())
        # with eps = 1 every env is mid-repeat: the held speed index, the greedy curvature index
        assert torch.equal(action // 3, explore.repeat)
        assert torch.equal(action % 3, greedy % 3)
        if held:  # an env mid-hold (before > 0) keeps its speed index
            assert torch.equal(explore.repeat[before > 0], held[-1][before > 0])
        held.append(explore.repeat.clone())
        assert bool((before <= 3).all())  # at most max_duration - 1 left after a start
    # the speed index changes only where a repeat started, so runs have drawn lengths
    changes = sum(int((a != b).sum()) for a, b in zip(held, held[1:], strict=False))
    assert 0 < changes <= starts
    assert set(torch.cat(held).tolist()) == {0, 1, 2}


def test_ez_speed_at_epsilon_zero_is_greedy():
    explore = make_exploration(1.0, 0.0, 1, kind="ez_speed", num_envs=3)
    explore.step(1)
    greedy = torch.tensor([0, 4, 8])
    assert explore(TensorDict({"action": greedy.clone()}, [3]))["action"].tolist() == [0, 4, 8]


@pytest.mark.parametrize("kind", ["epsilon", "speed_only", "ez_greedy", "ez_speed"])
def test_a_proposal_is_what_the_same_draws_give_another_greedy_action(kind):
    """``propose(g)`` after a step on greedy actions ``a`` equals that step run on ``g`` from
    the same generator and module state (the task head's proposal before a risk critic's mask)."""
    n = 16
    first, other = torch.zeros(n, dtype=torch.long), torch.arange(n) % 9

    def fresh():
        explore = make_exploration(0.5, 0.5, 10, kind=kind, num_envs=n, ez_max_duration=5)
        torch.manual_seed(3)
        return explore

    a, proposals, explored = fresh(), [], []
    for t in range(12):  # repeats under way, started and ended
        executed = a(td(n, step_count=torch.full((n,), t + 1)).set("action", first.clone()))["action"]
        proposals.append(a.propose(other))
        explored.append(executed != first)
        # explored envs: the same draw (ez_speed: the same speed change; a draw equal to
        # ``first`` is not told apart)
        part = (lambda x: x // 3) if kind == "ez_speed" else (lambda x: x)
        assert torch.equal(part(proposals[-1][explored[-1]]), part(executed[explored[-1]]))
    b = fresh()  # the same generator state from the start
    for t in range(12):
        direct = b(td(n, step_count=torch.full((n,), t + 1)).set("action", other.clone()))["action"]
        assert torch.equal(proposals[t], direct), t
    explored = torch.stack(explored)
    assert bool(explored.any()) and not bool(explored.all())


def test_boltzmann_has_no_proposal_before_the_mask():
    explore = make_exploration(1.0, 1.0, 10, kind="boltzmann")
    explore(td(4, q=torch.zeros(4, 9)))
    with pytest.raises(ValueError, match="boltzmann draws from the masked values"):
        explore.propose(torch.zeros(4, dtype=torch.long))
