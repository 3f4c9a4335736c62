"""Other libraries' agents under the Table III protocol (``policy=python``, ``policy=sb3``):
the same network through either adapter drives exactly the episodes ``policy=checkpoint`` does,
and a bad target, file or output is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from memrl.checkpoint import load_policy, load_qnet
from memrl.errors import UserError
from memrl.evaluate import evaluate
from memrl.evaluation.policies import run_config
from memrl.modules.policy import GreedyPolicy
from tests.eval_helpers import fake_run
from tests.helpers import csv_rows, inside_hydra_run

SMALL = ["protocol.episodes=3", "protocol.duration=25", "workers=1", "batch=2", "progress=false"]


class Unpicklable:
    """An agent with ``act(obs)`` that cannot be pickled (worker processes build their own)."""

    def __init__(self, run: str) -> None:
        self.policy = load_policy(run)  # memrl's own gym-face policy (docs/environments.md)

    def act(self, obs: np.ndarray) -> int:
        return self.policy.act(obs)

    def __reduce__(self):
        raise TypeError("not picklable")


def gym_agent(run: str) -> Unpicklable:
    return Unpicklable(run)


class PixelsAgent:
    """An agent with ``act_pixels``: a batch of uint8 stacks in, actions out."""

    def __init__(self, run: str) -> None:
        self.policy = GreedyPolicy(load_qnet(run)[0])

    def act_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.policy.act_batch(pixels)


class BadAgent:
    def act(self, obs: np.ndarray) -> int:
        return 9


def not_an_agent() -> object:
    return object()


@pytest.fixture
def run_and_env(tmp_path, compose_cfg):
    """A run folder (seeded untrained Table I network) and the gym config it acts in."""
    run = fake_run(tmp_path, compose_cfg)
    env = dict(run_config(run)["env"])
    env.pop("frame_stack")  # the runners stack 4 frames, as gym's frame_stack: 4
    return run, env


def evaluate_with(compose_cfg, overrides, env=None, out=None):
    cfg = compose_cfg("evaluate", [*overrides, *SMALL])
    if env is not None:
        with open_dict(cfg):
            cfg.policy.env = env
    (result,) = evaluate(cfg, out_dir=out)
    return result


def episodes_of(result) -> list[dict[str, str]]:
    return csv_rows(result.path / "episodes.csv")


@pytest.mark.parametrize("workers", [1, 2])
def test_python_agent_drives_the_checkpoints_episodes(run_and_env, compose_cfg, tmp_path, workers):
    run, env = run_and_env
    reference = evaluate_with(compose_cfg, [f"policy.run={run}"], out=tmp_path / "ref")
    overrides = ["policy=python", "policy.target=tests.test_external:gym_agent",
                 f"+policy.kwargs.run={run}", f"workers={workers}"]
    ours = evaluate_with(compose_cfg, overrides, env, tmp_path / "py")
    assert episodes_of(ours) == episodes_of(reference) and len(episodes_of(ours)) == 6
    assert (ours.name, ours.unit) == ("gym_agent", "tests.test_external:gym_agent")
    # in the gym env's own defaults (no drawn paths) the same network drives other episodes
    other = evaluate_with(compose_cfg, overrides, None, tmp_path / "py_plain")
    assert episodes_of(other) != episodes_of(reference)


def test_an_act_pixels_agent_runs_on_the_engine_with_the_same_episodes(run_and_env, compose_cfg, tmp_path,
                                                                       monkeypatch):
    from memrl.evaluation import runner

    run, env = run_and_env
    reference = evaluate_with(compose_cfg, [f"policy.run={run}"], out=tmp_path / "ref")
    calls, original = [], runner.run_jobs_on_engine
    monkeypatch.setattr(runner, "run_jobs_on_engine", lambda *a, **k: calls.append(1) or original(*a, **k))
    ours = evaluate_with(compose_cfg, ["policy=python", "policy.target=tests.test_external:PixelsAgent",
                                       f"+policy.kwargs.run={run}"], env, tmp_path / "px")
    assert calls and episodes_of(ours) == episodes_of(reference)


def _sb3_model_of(run, path):
    """A Stable-Baselines3 DQN whose Q-values are the run's network's: the memrl network as the
    features extractor (9 features), an identity layer as SB3's Q head. Its forward differs from
    the evaluation's only in memory layout (contiguous against channels-last), a few fp32 ulps
    of Q, far below this network's action gaps."""
    import gymnasium as gym
    from stable_baselines3 import DQN

    import memrl.envs  # noqa: F401

    model = DQN("CnnPolicy", gym.make("memrl/LaneChange-v0", config={"frame_stack": 4}), buffer_size=10,
                policy_kwargs={"features_extractor_class": MemrlFeatures, "net_arch": [],
                               "normalize_images": False}, device="cpu")
    net, _ = load_qnet(run)
    with torch.no_grad():
        for q in (model.q_net, model.q_net_target):
            q.features_extractor.net.load_state_dict(net.state_dict())
            (linear,) = q.q_net
            linear.weight.copy_(torch.eye(9))
            linear.bias.zero_()
    model.save(path)
    return path


try:
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class MemrlFeatures(BaseFeaturesExtractor):
        """memrl's Table I network as an SB3 features extractor (its 9 Q-values as features)."""

        def __init__(self, observation_space, features_dim: int = 9) -> None:
            from memrl.modules.qnet import QNetwork

            super().__init__(observation_space, features_dim)
            self.net = QNetwork()

        def forward(self, obs: torch.Tensor) -> torch.Tensor:
            return self.net(obs)
except ImportError:  # SB3 is an optional extra ([sb3], in [dev])
    MemrlFeatures = None  # type: ignore[assignment,misc]


def test_sb3_model_drives_the_checkpoints_episodes(run_and_env, compose_cfg, tmp_path):
    pytest.importorskip("stable_baselines3")
    run, env = run_and_env
    reference = evaluate_with(compose_cfg, [f"policy.run={run}"], out=tmp_path / "ref")
    path = _sb3_model_of(run, tmp_path / "dqn_memrl.zip")
    ours = evaluate_with(compose_cfg, ["policy=sb3", f"policy.path={path}"], env, tmp_path / "sb3")
    assert episodes_of(ours) == episodes_of(reference)
    assert (ours.name, ours.unit) == ("SB3 DQN", "dqn_memrl")


@pytest.mark.parametrize(("overrides", "line"), [
    (["policy=python"], "config 'policy.target': missing"),
    (["policy=python", "policy.target=tests.test_external:nope"],
     "config 'policy.target': cannot import 'tests.test_external:nope' (AttributeError"),
    (["policy=python", "policy.target=no_such_module:make"], "cannot import 'no_such_module:make'"),
    (["policy=python", "policy.target=tests.test_external:gym_agent"],
     "config 'policy.target': tests.test_external:gym_agent(**policy.kwargs) failed (TypeError: "),
    (["policy=python", "policy.target=tests.test_external:not_an_agent"],
     "gave a object with neither act(obs) nor act_pixels(pixels)"),
    (["policy=python", "policy.target=tests.test_external:BadAgent"],
     "tests.test_external:BadAgent: act returned 9: want 1 action index(es) in 0-8"),
    (["policy=python", "policy.target=tests.test_external:gym_agent", "policy.env={frame_stack:2}"],
     "config 'policy.env.frame_stack': the protocol gives agents 4 stacked frames, got 2"),
    (["policy=python", "policy.target=tests.test_external:BadAgent", "policy.env={lanes_count:0}"],
     "config 'policy.env': "),
    (["policy=sb3", "policy.path=/nonexistent/model.zip"], "config 'policy.path': no such file"),
    (["policy=sb3", "policy.path=/dev/null", "policy.algo=Nope"], "config 'policy.algo': 'Nope' is not"),
])
def test_bad_agents_are_refused_in_one_line(compose_cfg, tmp_path, overrides, line):
    if "policy=sb3" in overrides:
        pytest.importorskip("stable_baselines3")
    with pytest.raises(UserError) as err:
        evaluate_with(compose_cfg, overrides, out=tmp_path)
    message = str(err.value)
    assert line in message and "\n" not in message
    assert not any(tmp_path.iterdir())  # nothing written


def test_a_file_that_is_not_a_model_is_refused_by_name(compose_cfg, tmp_path):
    pytest.importorskip("stable_baselines3")
    path = tmp_path / "garbled.zip"
    path.write_bytes(b"not a zip")
    with pytest.raises(UserError, match=f"{path}: not a Stable-Baselines3 DQN model"):
        evaluate_with(compose_cfg, ["policy=sb3", f"policy.path={path}"], out=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_the_worked_example_puts_an_sb3_row_beside_memrls_in_a_report(run_and_env, compose_cfg, tmp_path):
    """docs/evaluation.md's worked example at a tiny size: tools/sb3_dqn.py trains, policy=sb3
    evaluates on the protocol's scenes, the report gives its row beside the memrl run's."""
    pytest.importorskip("stable_baselines3")
    import csv
    import importlib.util
    from pathlib import Path

    from memrl.report import report

    path = Path(__file__).parents[1] / "tools" / "sb3_dqn.py"
    spec = importlib.util.spec_from_file_location("sb3_dqn", path)
    tool = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(tool)  # type: ignore[union-attr]
    model = tool.train(64, tmp_path / "sb3" / "dqn_lane.zip")
    run, _ = run_and_env
    evaluate_with(compose_cfg, [f"policy.run={run}"], out=tmp_path / "ref")
    evaluate_with(compose_cfg, ["policy=sb3", f"policy.path={model}"], tool.ENV, tmp_path / "sb3" / "eval")
    runs = f"runs=[{run},{tmp_path / 'sb3' / 'eval'}]"
    files = report(compose_cfg("report", [runs, "evaluate_missing=false", "rollouts.rows=[SB3 DQN]",
                                          "rollouts.video=false", "progress=false", "n_resamples=200",
                                          "fig5=false"]), out_dir=tmp_path / "report")
    with files.table_csv.open() as f:
        methods = {r["method"] for r in csv.DictReader(f)}
    assert methods == {"Default", "SB3 DQN"}
    assert "| SB3 DQN |" in files.markdown
    assert [p.name for p in files.strips][:1] == ["fig7_SB3_DQN.png"]  # replayed from its eval.json


def test_the_go_on_command_of_a_stopped_evaluation_names_the_agent_as_given(tmp_path):
    """A stopped ``policy=python`` evaluation's printed command gives the same agent again: its
    target outside Hydra, the call's own ``policy`` overrides (kwargs, env) inside it."""
    import types

    from memrl.evaluation.session import resume_command

    out = tmp_path / "ev"
    cand = types.SimpleNamespace(name="gym_agent", meta={"kind": "python", "target": "m:make"})
    command = "python -m memrl.evaluate"
    assert resume_command(cand, out) == f"{command} policy=python policy.target=m:make resume={out}"
    sb3 = types.SimpleNamespace(name="SB3 DQN", meta={"kind": "sb3", "path": "/x/dqn.zip"})
    assert resume_command(sb3, out) == f"{command} policy=sb3 policy.path=/x/dqn.zip resume={out}"
    given = ["policy=python", "policy.target=m:make", "+policy.kwargs.run=/r", "policy.env={frame_stack:4}"]
    line = inside_hydra_run("evaluate", [*given, "protocol.episodes=3"], lambda: resume_command(cand, out))
    assert line == (f"{command} policy=python policy.target=m:make +policy.kwargs.run=/r "
                    f"'policy.env={{frame_stack:4}}' resume={out}")
