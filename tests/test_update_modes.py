"""``agent.update_mode=compiled`` (the whole gradient step ``torch.compile``d) against the eager
step, and ``agent.loss_readback`` against a read per update."""

from __future__ import annotations

import pytest
import torch

from memrl.benchmarks.synthetic import episodes
from memrl.dqn.builder import StageInputs, build_stage
from memrl.dqn.learner import Learner
from memrl.modes import mode_of
from memrl.modules.qnet import network_for_task
from memrl.train import train
from tests.helpers import tiny

UPDATES = 200
CASES = {  # name: (train overrides, stages with their update counts)
    "default": ([], (("default", UPDATES),)),
    "A": (["+mode=A"], (("A", UPDATES),)),
    "B": (["+mode=B"], (("B1", UPDATES // 2), ("B2", UPDATES // 2))),
    "c51": (["network=c51"], (("default", UPDATES),)),
    "hlgauss": (["network=hlgauss"], (("default", UPDATES),)),
    "risk": (["network=risk"], (("default", UPDATES),)),
}


def batches_of(cfg, demos, stages, seed: int = 0):
    """Each stage's terms and its sampled batches: the real stage buffers (agent data made by
    :mod:`memrl.benchmarks.synthetic`), sampled once so that both learners see the same."""
    spec, nodes, out = mode_of(cfg), StageInputs.of(cfg), []
    torch.manual_seed(seed)
    for name, n in stages:
        stage = build_stage(spec.stage(name), nodes, demos, 1, torch.device("cpu"))
        if not stage.offline:
            for ep in episodes(600, seed):
                stage.buffer.extend(ep)
        out.append((stage, [stage.buffer.sample() for _ in range(n)]))
    return out


def make_learner(cfg, mode: str, device: str = "cpu") -> Learner:
    cfg.agent.update_mode = mode
    torch.manual_seed(1)  # both learners start from the same weights
    return Learner(cfg.agent, device, network=network_for_task(cfg.network, cfg.env, float(cfg.agent.gamma)))


def copy_state(dst: Learner, src: Learner) -> None:
    """``src``'s online and target weights and Adam moments into ``dst``'s own tensors, in place
    (new tensors would be new inputs to the compiled step: a recompile per update)."""
    with torch.no_grad():
        for a, b in zip(dst.loss_module.state_dict().values(), src.loss_module.state_dict().values(),
                        strict=True):
            a.copy_(b)
        pairs = zip(dst.optimizer.param_groups[0]["params"], src.optimizer.param_groups[0]["params"],
                    strict=True)
        for a, b in pairs:
            for key, value in src.optimizer.state.get(b, {}).items():
                dst.optimizer.state[a][key].copy_(value)


# A float32 sum of n terms is within n u of the exact one (u = 2^-24, the unit roundoff); the
# longest reduction of an update is the FC layer's 16 x 10 x 10 = 1,600 inputs: the eager and the
# compiled step (whose kernels sum in another order) agree within 2 x 1,600 u of each other.
RTOL = 2 * 1600 * 2.0 ** -24


def lockstep(cfg, staged, mode: str = "compiled", device: str = "cpu") -> Learner:
    """Eager and compiled learners stepped side by side over the staged batches, the compiled one
    set to the eager one's state before each update (differences cannot compound): every
    update's loss and clipped gradient agree within :data:`RTOL`, and the weights after it
    within Adam's bound (each moves by at most lr per step)."""
    eager, compiled = make_learner(cfg, "eager", device), make_learner(cfg, mode, device)
    for i, (stage, batches) in enumerate(staged):
        fresh = i > 0 and stage.spec.fresh_optimizer
        for learner in (eager, compiled):
            learner.start_stage(stage.terms, stage.lr, fresh_optimizer=fresh)
        for k, batch in enumerate(batches):
            copy_state(compiled, eager)
            batch = batch.to(device)
            loss_e, loss_c = eager.step(batch.clone()), compiled.step(batch.clone())
            where = f"{stage.name} update {k}"
            assert abs(float(loss_c) - float(loss_e)) <= RTOL * abs(float(loss_e)) + 1e-12, where
            grads = [(p.grad, q.grad) for p, q in zip(eager.qnet.parameters(), compiled.qnet.parameters(),
                                                       strict=True) if p.grad is not None]
            assert grads and all(q is not None for _, q in grads), where
            ge, gc = torch.cat([g.flatten() for g, _ in grads]), torch.cat([g.flatten() for _, g in grads])
            assert float((gc - ge).norm()) <= RTOL * float(ge.norm()) + 1e-12, where
            lr = eager.optimizer.param_groups[0]["lr"]
            for (name, x), y in zip(eager.qnet.state_dict().items(), compiled.qnet.state_dict().values(),
                                    strict=True):
                assert float((x - y).abs().max()) <= 2 * lr, (where, name)
    assert compiled.update_mode == mode and compiled.updates == eager.updates
    return compiled


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # as training runs (agent.threads); inductor's compile is no faster with 2
    yield
    torch.set_num_threads(before)


@pytest.mark.slow  # 1-2 minutes each: inductor compiles the step's forward and backward
@pytest.mark.parametrize("case", list(CASES))
def test_the_compiled_update_equals_the_eager_one(compose_cfg, demos, one_thread, case):
    """Default, A, B1 then B2 (a fresh Adam, a new trace) and each value head: 200 updates of
    the compiled step against the eager step (float32: the rounding above)."""
    overrides, stages = CASES[case]
    cfg = compose_cfg("train", ["+experiment=smoke", "agent.batch_size=8", "agent.precision=float32",
                                "buffer.capacity=1000", *overrides])
    staged = batches_of(cfg, demos, stages)
    torch._dynamo.reset()
    with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True):  # no quiet fall back to eager
        lockstep(cfg, staged)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("case", ["default", "B"])
def test_the_captured_update_equals_the_eager_one_on_cuda(compose_cfg, demos, case, monkeypatch):
    """On a GPU: the CUDA-graph step against the eager one, as on the CPU (full float32: no TF32)."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_tf32", False)
    overrides, stages = CASES[case]
    cfg = compose_cfg("train", ["+experiment=smoke", "agent.batch_size=32", "agent.precision=float32",
                                "buffer.capacity=1000", "device=cuda", *overrides])
    staged = batches_of(cfg, demos, stages)
    torch._dynamo.reset()
    with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True):
        lockstep(cfg, staged, "captured", "cuda")


def test_captured_needs_a_cuda_device(compose_cfg):
    cfg = compose_cfg("train", ["+experiment=smoke", "agent.update_mode=captured", "device=cpu"])
    with pytest.raises(ValueError, match="agent.update_mode=captured needs a CUDA device"):
        Learner(cfg.agent)


def test_a_failed_compile_falls_back_to_the_eager_step_with_a_warning(compose_cfg, monkeypatch):
    def broken(fn, **kwargs):
        def call(*args):
            raise RuntimeError("inductor: no C++ compiler")
        return call

    monkeypatch.setattr(torch, "compile", broken)
    cfg = compose_cfg("train", ["+experiment=smoke", "agent.update_mode=compiled", "agent.batch_size=4"])
    learner = Learner(cfg.agent)
    batch = batches_of(cfg, None, (("default", 1),))[0][1][0]
    with pytest.warns(RuntimeWarning, match="agent.update_mode=compiled: compiled update failed"):
        loss = learner.step(batch)
    assert learner.update_mode == "eager" and learner.updates == 1 and float(loss) > 0


@pytest.mark.parametrize("mode", [None, "B"])
def test_reading_losses_back_every_k_updates_logs_the_same_values(compose_cfg, tmp_path, demos, mode):
    """updates.csv and the checkpoint's accumulators are the same whether the losses are read
    every update or 7 at a time (a k that divides neither log_every nor the stage-1 checks)."""
    rows = []
    for k in (1, 7):
        cfg = compose_cfg("train", [*tiny(mode), "total_episodes=4", f"agent.loss_readback={k}"])
        out = tmp_path / f"k{k}"
        train(cfg, out, demos=demos)
        text = (out / "updates.csv").read_text().splitlines()
        header = text[0].split(",")
        keep = [i for i, name in enumerate(header) if not name.endswith("_per_s")]  # wall clock
        rows.append([[line.split(",")[i] for i in keep] for line in text])
        state = torch.load(out / "checkpoints" / "last" / "state.pt", weights_only=False)
        rows[-1].append(state["acc"])
    assert len(rows[0]) > 3 and rows[0] == rows[1]
