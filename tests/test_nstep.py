"""n-step returns on the replay side (memrl.data.nstep): hand computations, every buffer kind,
the TD target DQNLoss sees, the real collector, demos with gaps, n = 1 unchanged."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer, demo_buffer
from memrl.data.nstep import STEPS_KEY
from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from tests.nstep_ref import reference
from tests.stream_data import stream_steps

G = 0.5


def episode(rewards, end: str, first_id: int = 1, size: int = 4) -> list[TensorDict]:
    """One stream's episode as 1-step [1] rows; ``end``: crash (terminated) or limit."""
    from tests.stream_data import frame

    def stack(ids):
        return torch.stack([torch.from_numpy(frame(k, size)) for k in ids])

    ids, rows = [first_id] * 4, []
    for i, r in enumerate(rewards):
        nxt = ids[1:] + [first_id + i + 1]
        last = i == len(rewards) - 1
        rows.append(TensorDict({
            "pixels": stack(ids)[None], "action": torch.tensor([i]),
            "is_demo": torch.tensor([False]),
            "next": {"pixels": stack(nxt)[None], "reward": torch.tensor([[float(r)]]),
                     "done": torch.tensor([[last]]),
                     "terminated": torch.tensor([[last and end == "crash"]]),
                     "truncated": torch.tensor([[last and end == "limit"]])}}, [1]))
        ids = nxt
    return rows


def all_rows(buffer):
    return buffer.storage.get(torch.arange(len(buffer)))


@pytest.mark.parametrize("compact", [True, False])
def test_hand_computed_three_step_targets_with_a_crash_and_a_time_limit(compact):
    # episode 1: rewards 1, 2, 4, 8 then a crash; episode 2: 16, 32 then the time limit
    steps = episode([1, 2, 4, 8], "crash") + episode([16, 32], "limit", first_id=100)
    rb = agent_buffer(100, 4, compact=compact, n_step=3, gamma=G)
    for td in steps:
        rb.extend(td)
    got = all_rows(rb)
    assert got["next", "reward"].reshape(-1).tolist() == [
        1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4 + 0.25 * 8, 4 + 0.5 * 8, 8, 16 + 0.5 * 32, 32]
    assert got[STEPS_KEY].reshape(-1).tolist() == [3, 3, 2, 1, 2, 1]
    # crash within the window: terminated, no bootstrap; the time limit: bootstraps
    assert got["next", "terminated"].reshape(-1).tolist() == [False, True, True, True, False, False]
    assert got["next", "done"].reshape(-1).tolist() == [False, True, True, True, True, True]
    for i, last in enumerate([2, 3, 3, 3, 5, 5]):
        assert torch.equal(got["next", "pixels"][i], steps[last]["next", "pixels"][0])
        assert torch.equal(got["pixels"][i], steps[i]["pixels"][0])


def test_the_td_target_dqnloss_sees_uses_gamma_to_the_steps_and_the_crash_mask():
    steps = episode([1, 2, 4, 8], "crash") + episode([16, 32, 64], "limit", first_id=100)
    rb = agent_buffer(100, 4, compact=True, n_step=3, gamma=G)
    for td in steps:
        rb.extend(td)
    batch = all_rows(rb)
    learner = Learner(AgentConfig(gamma=G))
    v = torch.arange(1.0, 8.0).reshape(-1, 1) * 100  # a stand-in max_a Q_target(s_{t+m}, a)
    target = learner.loss_module.value_estimator.value_estimate(batch.clone(), next_value=v)
    hand = [1 + 0.5 * 2 + 0.25 * 4 + 0.125 * 100,  # 3 steps, bootstrap gamma^3
            2 + 0.5 * 4 + 0.25 * 8,  # reaches the crash: no bootstrap
            4 + 0.5 * 8, 8,
            16 + 0.5 * 32 + 0.25 * 64 + 0.125 * 500,  # ends at the time limit: bootstraps
            32 + 0.5 * 64 + 0.25 * 600, 64 + 0.5 * 700]
    assert target.reshape(-1).tolist() == hand


@pytest.mark.parametrize("n", [1, 3, 10])
@pytest.mark.parametrize("compact", [True, False])
def test_interleaved_streams_match_the_reference_at_every_row(n, compact):
    streams = 3
    steps = stream_steps(streams, 40, seed=n, max_len=9)
    rb = agent_buffer(400, 8, compact=compact, streams=streams, n_step=n, gamma=0.9)
    for td in steps:
        rb.extend(td)
    got, want = all_rows(rb), reference(steps, n, 0.9)
    for i, w in enumerate(want):
        assert torch.equal(got["next", "reward"][i], w["reward"]), i
        assert int(got[STEPS_KEY][i]) == w["m"] if n > 1 else STEPS_KEY not in got.keys()
        assert bool(got["next", "terminated"][i]) == w["terminated"]
        assert bool(got["next", "done"][i]) == w["done"]
        assert torch.equal(got["next", "pixels"][i], w["next_pixels"]), i


def test_n_1_samples_exactly_what_a_plain_buffer_samples():
    steps = stream_steps(2, 30, seed=4)
    plain, one = agent_buffer(40, 8, streams=2), agent_buffer(40, 8, streams=2, n_step=1, gamma=G)
    for td in steps:
        plain.extend(td)
        one.extend(td)
    torch.manual_seed(0)
    a = [plain.sample() for _ in range(3)]
    torch.manual_seed(0)
    b = [one.sample() for _ in range(3)]
    assert all((x == y).all() and set(x.keys(True)) == set(y.keys(True)) for x, y in zip(a, b, strict=True))
    assert type(plain.storage) is type(one.storage)


def test_windows_stay_right_after_the_fifo_wraps_and_across_a_checkpoint(tmp_path):
    streams, steps = 2, stream_steps(2, 50, seed=7, max_len=6)
    rb = agent_buffer(26, 8, streams=streams, n_step=4, gamma=0.9)  # not a multiple of S
    for td in steps:
        rb.extend(td)
    want = reference(steps, 4, 0.9)
    # slot of row w (write order) is w % 26; the newest 26 rows are live
    live = range(len(want) - 26, len(want))
    got = rb.storage.get(torch.tensor([w % 26 for w in live]))
    for k, w in enumerate(live):
        assert torch.equal(got["next", "reward"][k], want[w]["reward"]), w
        assert int(got[STEPS_KEY][k]) == want[w]["m"]
    rb.dumps(tmp_path / "rb")
    again = agent_buffer(26, 8, streams=streams, n_step=4, gamma=0.9)
    again.loads(tmp_path / "rb")
    more = stream_steps(2, 60, seed=7, max_len=6)[50:]  # the same streams, continued
    for buf in (rb, again):
        for td in more:
            buf.extend(td)
    idx = torch.arange(26)
    assert (rb.storage.get(idx) == again.storage.get(idx)).all()


@pytest.mark.parametrize("n", [1, 3, 10])
def test_demos_chain_consecutive_transitions_and_stop_at_gaps(n):
    ep = episode([1, 2, 4, 8, 16, 32], "crash") + episode([3, 5, 7], "limit", first_id=50)
    rows = torch.cat(ep)
    kept = torch.cat([rows[:2], rows[3:]])  # transition 2 not stored (a noise step): a gap
    kept["is_demo"][:] = True
    for compact in (True, False):
        got = demo_buffer(kept, compact=compact, n_step=n, gamma=G)
        got = got.storage.get(torch.arange(len(kept)))
        # windows over the stored rows: [r0 r1] | [r3 r4 r5 crash] | [3 5 7 limit]
        chains = [[1, 2], [8, 16, 32], [3, 5, 7]]
        ends = ["gap", "crash", "limit"]
        want, term = [], []
        for chain, end in zip(chains, ends, strict=True):
            for i in range(len(chain)):
                w = chain[i:i + n]
                want.append(sum(G ** j * r for j, r in enumerate(w)))
                term.append(end == "crash" and i + n >= len(chain))
        assert got["next", "reward"].reshape(-1).tolist() == want
        assert got["next", "terminated"].reshape(-1).tolist() == term


def test_mode_a_buffer_windows_both_parts():
    demos = torch.cat(episode([1, 2, 4, 8], "crash"))
    demos["is_demo"][:] = True
    rb = PriorKnowledgeBuffer(demos, 40, 0.1, 4, n_step=3, gamma=G)
    for td in episode([10, 20, 40, 80], "limit", first_id=70):
        rb.extend(td)
    demo_part = rb.offline_buffer.storage.get(torch.arange(4))
    agent_part = rb.online_buffer.storage.get(torch.arange(4))
    assert demo_part["next", "reward"].reshape(-1).tolist() == [1 + 1 + 1, 2 + 2 + 2, 4 + 4, 8]
    assert agent_part["next", "reward"].reshape(-1).tolist() == [10 + 10 + 10, 20 + 20 + 20,
                                                                  40 + 40, 80]
    batch = rb.sample()
    assert STEPS_KEY in batch.keys() and len(batch) == 4


def test_n_step_below_one_names_the_key(compose_cfg, tmp_path):
    from memrl.errors import ConfigError
    from memrl.train import train
    from tests.helpers import TINY

    with pytest.raises(ConfigError, match=r"config 'agent.n_step': must be >= 1, got 0"):
        train(compose_cfg("train", TINY + ["agent.n_step=0"]), tmp_path / "run")


@pytest.mark.parametrize("n", [3, 10])
def test_real_collector_data_on_four_envs_matches_the_reference(compose_cfg, n):
    from memrl.dqn.collector import Collector
    from memrl.envs.vehicles import N_ACTIONS
    from tests.helpers import TINY

    cfg = compose_cfg("train", TINY + ["env.duration=10"])
    collector = Collector(cfg.env, 4, torch.device("cpu"), seed=5)
    gen = torch.Generator().manual_seed(0)

    def act(td, _frames):  # env 0 steers left into the wall, env 1 drives on, 2-3 at random
        a = torch.randint(N_ACTIONS, (4,), generator=gen)
        a[0], a[1] = 3, 4
        td["action"] = a

    steps = collector.collect(act, 36, 0).transitions
    collector.close()
    flags = torch.stack([s["next", "terminated"] for s in steps])
    assert flags[:, 0].any() and (torch.stack([s["next", "truncated"] for s in steps])).any()
    for compact in (True, False):
        rb = agent_buffer(400, 8, compact=compact, streams=4, n_step=n, gamma=0.95)
        for td in steps:
            rb.extend(td)
        got, want = all_rows(rb), reference(steps, n, 0.95)
        for i, w in enumerate(want):
            assert torch.equal(got["next", "reward"][i], w["reward"]), i
            assert int(got[STEPS_KEY][i]) == w["m"]
            assert bool(got["next", "terminated"][i]) == w["terminated"]
            assert torch.equal(got["next", "pixels"][i], w["next_pixels"]), i
        assert {w["m"] for w in want} >= {1, n}  # full windows and ones cut by an end


def test_the_learner_loss_is_eq_1_on_the_n_step_target():
    steps = episode([1, 2, 4, 8], "crash", size=84) + episode([16, 32, 64], "limit", 100, size=84)
    rb = agent_buffer(100, 4, compact=True, n_step=3, gamma=G)
    for td in steps:
        rb.extend(td)
    batch = all_rows(rb)
    learner = Learner(AgentConfig(gamma=G))
    with torch.no_grad():  # double DQN: the online net picks, the target net (a copy now) values
        q_next = learner.qnet(batch["next", "pixels"])
        v = q_next.gather(1, q_next.argmax(1, keepdim=True))
        m, term = batch[STEPS_KEY], batch["next", "terminated"]
        target = batch["next", "reward"] + G ** m * v * (~term)
        q = learner.qnet(batch["pixels"]).gather(1, batch["action"].reshape(-1, 1))
        hand = 0.5 * ((q - target) ** 2).mean()
        assert m.reshape(-1).tolist() == [3, 3, 2, 1, 3, 2, 1]
        torch.testing.assert_close(learner.loss(batch.clone()), hand, rtol=1e-6, atol=0)


def test_checkpoints_from_before_n_step_resume_as_one_step_runs():
    from memrl.checkpoint.resume import with_legacy_values

    assert with_legacy_values({"agent": {"gamma": 0.95}})["agent"]["n_step"] == 1


def test_stage_1_keeps_the_dataset_order_for_n_step_windows():
    from memrl.dqn.stage1 import split_demos

    demos = torch.cat(episode(list(range(20)), "crash"))
    shuffled, held = split_demos(demos, 0.2, seed=3)
    ordered, held2 = split_demos(demos, 0.2, seed=3, keep_order=True)
    assert (held == held2).all()  # the same demos held out
    rewards = ordered["next", "reward"].reshape(-1)
    assert torch.equal(rewards, rewards.sort().values)
    assert sorted(shuffled["next", "reward"].reshape(-1).tolist()) == rewards.tolist()
