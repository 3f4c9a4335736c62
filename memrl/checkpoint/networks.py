"""Q-network files: a run's ``final.pt`` and mode B's ``checkpoints/stage1.pt``, written and read.

The weights and their checksum go through :mod:`memrl.checkpoint.weights`; the network is built
from the architecture the file stores (:mod:`memrl.modules.qnet`), and a file whose weights do
not fit it is refused by name (:class:`~memrl.checkpoint.errors.CheckpointError`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from memrl.checkpoint.errors import CheckpointError
from memrl.checkpoint.weights import load_weights, save_weights
from memrl.data.demos import hashed_env_config
from memrl.errors import load_run_config
from memrl.modules.qnet import TABLE1, arch_of, build_qnet

log = logging.getLogger(__name__)


def resolve(path: str | Path) -> Path:
    """A run folder, its ``checkpoints/`` folder or a ``final.pt`` file -> the ``final.pt``."""
    p = Path(path)
    for candidate in (p, p / "final.pt", p / "checkpoints" / "final.pt"):
        if candidate.is_file():
            return candidate
    raise CheckpointError(f"{path}: no trained network found (expected a run folder with "
                          "checkpoints/final.pt, or a final.pt file)")


def save_qnet(path: str | Path, net: torch.nn.Module, env_cfg: dict[str, Any],
              extra: dict[str, Any] | None = None) -> Path:
    """Write a network in the ``final.pt`` format (``qnet`` weights, ``network`` architecture,
    ``env`` config, extras), with its checksum (:func:`memrl.checkpoint.weights.save_weights`)."""
    weights = {k: v.cpu() for k, v in net.state_dict().items()}  # loads on any device
    return save_weights(path, {"qnet": weights, "network": arch_of(net), "env": env_cfg, **(extra or {})})


OFFLINE_WEIGHTS = "stage1.pt"
"""The file (in a run's ``checkpoints/``) that holds the weights an offline stage ends with
(:attr:`memrl.modes.StageSpec.settings`): the stage-1 network of the paper's mode B, which the
next stage starts from, ``mode.stage1.init`` shares and evaluation reads (``weights=stage1``)."""


def save_offline(checkpoints: Path, loss_module: torch.nn.Module, net: torch.nn.Module,
                 progress: dict[str, Any]) -> Path:
    """Write an offline stage's end state, ``checkpoints/stage1.pt``: the loss module's weights
    (online and target networks), the architecture loaders rebuild, the stop rule's record."""
    return save_weights(checkpoints / OFFLINE_WEIGHTS, {"loss_module": loss_module.state_dict(),
                                                        "network": arch_of(net), "stage1": progress})


def stored_arch(state: dict[str, Any]) -> dict[str, Any]:
    """The architecture a weights file stores; Table I for files written before they did."""
    arch = state.get("network")
    return dict(TABLE1 if arch is None else arch)


def qnet_from(file: Path, arch: dict[str, Any], weights: dict[str, Any],
              net: torch.nn.Module | None = None) -> torch.nn.Module:
    """The network of ``arch`` (``net``: already built from it) with ``weights``, in eval mode;
    a network that ``arch`` cannot build, or weights of another architecture, are refused
    naming ``file``."""
    net = _build(file, arch) if net is None else net
    want = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    have = {k: tuple(getattr(v, "shape", ())) for k, v in weights.items()}
    if want != have:
        missing, extra = sorted(set(want) - set(have)), sorted(set(have) - set(want))
        shapes = sorted(k for k in set(want) & set(have) if want[k] != have[k])
        what = "; ".join(f"{label} {', '.join(keys[:3])}{' ...' if len(keys) > 3 else ''}"
                         for label, keys in (("missing", missing), ("unexpected", extra),
                                             ("other shapes", shapes)) if keys)
        raise CheckpointError(f"{file}: its weights do not match its network "
                              f"{describe(arch)} ({what})")
    net.load_state_dict(weights)
    return net.eval()


def _build(file: Path, arch: dict[str, Any]) -> torch.nn.Module:
    try:
        # Its initial weights are overwritten: drawing them from the global generator would
        # shift a run's own stream (learner init, replay sampling) by the nets it loads, e.g.
        # the opponent pool's, so a mixed-traffic run would start from other weights.
        with torch.random.fork_rng(devices=[]):
            return build_qnet(arch)
    except Exception as err:  # an unknown class or argument (Hydra's InstantiationException...)
        raise CheckpointError(f"{file}: cannot build its network {arch.get('_target_')!r} "
                              f"({str(err).splitlines()[0]})") from err


def describe(arch: dict[str, Any]) -> str:
    """``DuelingQNetwork(hidden=256, layernorm=True)``: the class and the arguments that differ
    from Table I's."""
    args = ", ".join(f"{k}={v!r}" for k, v in arch.items() if k != "_target_" and TABLE1.get(k) != v)
    return f"{str(arch.get('_target_')).rsplit('.', 1)[-1]}({args})"


def qnet_weights(state: dict[str, Any], names: set[str] | None = None,
                 prefix: str = "value_network_params.") -> dict[str, Any]:
    """The Q-network's weights inside a TorchRL ``DQNLoss`` state dict (the online network's,
    keys under ``prefix``; e.g. ``value_network_params.module.0.module.head.1.weight`` ->
    ``head.1.weight``); ``names``: the bare network's parameter names (None: Table I's)."""
    if names is None:
        with torch.random.fork_rng(devices=[]):  # only the names are wanted
            names = set(build_qnet(TABLE1).state_dict())
    out = {}
    for key, value in state.items():
        if not key.startswith(prefix):
            continue
        parts = key[len(prefix):].split(".")
        # the shortest tail that names a parameter of the bare network (wrappers add "module.N.")
        name = next((".".join(parts[i:]) for i in range(len(parts)) if ".".join(parts[i:]) in names), None)
        if name is not None:
            out[name] = value
    return out


def stage1_file(path: str | Path) -> Path:
    """``<run>/checkpoints/stage1.pt`` of a mode B run folder, its ``checkpoints`` folder or
    the file itself."""
    p = Path(path)
    candidates = (p, p / OFFLINE_WEIGHTS, p / "checkpoints" / OFFLINE_WEIGHTS)
    file = next((c for c in candidates if c.is_file()), None)
    if file is None:
        raise CheckpointError(f"{path}: no stage-1 network (expected checkpoints/stage1.pt of a mode B run)")
    return file


def stage1_source(path: str | Path, env_cfg: Any, network: Any | None = None) -> Path:
    """The stage-1 weights that ``mode.stage1.init`` names, checked: present, trained in the
    same env config as ``env_cfg`` (the pixels and the dynamics mean the same) when the run
    folder's ``config.yaml`` is there to tell, and, with ``network`` (a ``network`` config
    node), of that architecture. The reward (``env.reward``, ``env.shaping``) may differ, logged: stage 2
    fits its Q-values to its own run's reward, as it does to its own ``agent.gamma``."""
    file = stage1_file(path)
    state = check_stage1(file)
    if network is not None:
        stored = stored_arch(state)
        with torch.random.fork_rng(devices=[]):  # building draws initial weights
            net = build_qnet(network)
        ours = arch_of(net)
        base = base_arch(network)  # draws in its own forked generator
        scalar = scalar_arch(net)
        if stored not in (ours, base, scalar):
            nor = f" nor its base head {describe(base)}" if base is not None else ""
            nor += f" nor its scalar twin {describe(scalar)}" if scalar is not None else ""
            raise CheckpointError(f"{file}: its network {describe(stored)} is not this run's "
                                  f"{describe(ours)}{nor} (key network)")
    run_cfg = file.parent.parent / "config.yaml"
    if run_cfg.is_file():
        loaded = load_run_config(run_cfg)
        theirs = loaded.get("env") if isinstance(loaded, DictConfig) else None
        if theirs is not None:
            their_env, our_env = hashed_env_config(theirs), hashed_env_config(env_cfg)
            their_reward, our_reward = their_env.pop("reward", None), our_env.pop("reward", None)
            their_shaping, our_shaping = their_env.pop("shaping", None), our_env.pop("shaping", None)
            if their_env != our_env:
                raise CheckpointError(f"{file}: trained in another env config than this run's "
                                      f"(see {run_cfg}, key env)")
            if (their_reward, their_shaping) != (our_reward, our_shaping):
                log.info("%s: trained under the reward %s (shaping %s); stage 2 trains under this "
                         "run's %s (shaping %s)", file, their_reward, their_shaping or "off", our_reward,
                         our_shaping or "off")
    return file


def base_arch(network: Any) -> dict[str, Any] | None:
    """The architecture of the base head of a network that holds one beside a critic of its own
    (``network.base``: :mod:`memrl.modules.risk`), built alone with the network's frames, size
    and actions; None for a network without one."""
    node = network.get("base") if hasattr(network, "get") else None
    if node is None:
        return None
    task = {k: network[k] for k in ("frames", "size", "n_actions") if k in network}
    with torch.random.fork_rng(devices=[]):
        return arch_of(build_qnet({**task, **node}))


def scalar_arch(net: torch.nn.Module) -> dict[str, Any] | None:
    """For a categorical head (C51, HL-Gauss), the architecture of Table I's scalar network with
    the same trunk, whose stage-1 weights :func:`offline_state` converts; None for any other."""
    if not _is_categorical(net):
        return None
    arch = arch_of(net)
    return {**TABLE1, **{k: arch[k] for k in TABLE1 if k != "_target_" and k in arch}}


def _last_linear(qnet: torch.nn.Module) -> str:
    """The parameter prefix of a categorical network's output layer (``head.3``)."""
    last = len(qnet.head) - 1  # type: ignore[arg-type]
    return f"head.{last}"


BASE = ".module.0.module."
"""Where a ``DQNLoss`` state dict's keys name the Q-network's own parameters."""


def offline_state(state: dict[str, Any], loss_module: torch.nn.Module,
                  qnet: torch.nn.Module | None = None) -> dict[str, Any]:
    """The ``loss_module`` state to load from stage-1 weights ``state`` (:func:`stage1_source`
    has checked them): theirs as stored for the same network; for a network with a critic
    beside a base head of the stored architecture (``network=risk`` from a stage 1 trained
    without one), the base's online and target weights theirs, the critic's its own; for a
    categorical head ``qnet`` (C51, HL-Gauss) from Table I's scalar network of the same trunk,
    theirs with the output layer converted (:meth:`CategoricalQNetwork.head_from_scalar`:
    the same Q-values, online and target)."""
    theirs, ours = state["loss_module"], loss_module.state_dict()
    support = {k for k in set(ours) - set(theirs) if k.endswith(f"{BASE}support")}
    if support and _is_categorical(qnet):  # a categorical head's fixed support (from its arch): its own
        theirs = {**theirs, **{k: ours[k] for k in support}}
    if set(theirs) == set(ours):
        differ = [k for k in ours if tuple(ours[k].shape) != tuple(theirs[k].shape)]
        if not differ:
            return theirs
        return _converted(theirs, ours, differ, qnet)
    mapped = dict(ours)
    for key, value in theirs.items():
        head, sep, rest = key.partition(BASE)
        new = f"{head}{BASE}base.{rest}" if sep else key
        if new not in ours or tuple(ours[new].shape) != tuple(value.shape):
            raise CheckpointError(f"stage-1 weights: {key} has no place in this run's network")
        mapped[new] = value
    return mapped


def load_stage1_qnet(path: str | Path) -> torch.nn.Module:
    """The Q-network at the end of mode B's stage 1: ``<run>/checkpoints/stage1.pt`` (or that
    file), saved by the trainer as ``{"loss_module": DQNLoss state, "network": architecture,
    "stage1": ...}``; a file in the ``final.pt`` format (``{"qnet": ...}``) is read as such."""
    file = stage1_file(path)
    state = load_weights(file, "stage-1 weights")
    try:
        arch = stored_arch(state)
        weights = state["qnet"] if "qnet" in state else state["loss_module"]
    except Exception as err:  # a dict of something else
        raise CheckpointError(f"{file}: not a memrl stage-1 checkpoint ({err!r})") from err
    net = _build(file, arch)
    if "qnet" not in state:
        weights = qnet_weights(weights, set(net.state_dict()))
    return qnet_from(file, arch, weights, net)


def load_qnet(path: str | Path) -> tuple[torch.nn.Module, dict[str, Any]]:
    """The Q-network of a finished run (built from the architecture its file stores) and the
    env config it was trained with."""
    file = resolve(path)
    state = load_weights(file, "Q-network weights")
    try:
        arch, weights = stored_arch(state), state["qnet"]
    except Exception as err:  # a dict of something else
        raise CheckpointError(f"{file}: not a memrl Q-network checkpoint ({err!r})") from err
    return qnet_from(file, arch, weights), state.get("env", {})


def check_stage1(file: Path) -> dict[str, Any]:
    """Refuse a ``stage1.pt`` that is missing, truncated, altered (its checksum) or not a
    stage-1 record, by name; its content when sound."""
    if not file.is_file():
        raise CheckpointError(f"{file}: missing (mode B's stage-1 weights; stage 2 starts from them)")
    state = load_weights(file, "stage-1 weights")
    if "loss_module" not in state:
        raise CheckpointError(f"{file}: not a stage-1 record (no 'loss_module' weights)")
    return state


def _is_categorical(qnet: torch.nn.Module | None) -> bool:
    from memrl.modules.categorical import CategoricalQNetwork

    return isinstance(qnet, CategoricalQNetwork)


def _converted(theirs: dict[str, Any], ours: dict[str, Any], differ: list[str],
               qnet: torch.nn.Module | None) -> dict[str, Any]:
    """``theirs`` with the scalar output layers ``differ`` (online and target) converted to the
    categorical head ``qnet``'s; any other difference is refused."""
    from memrl.modules.categorical import CategoricalQNetwork

    if not isinstance(qnet, CategoricalQNetwork):
        raise CheckpointError(f"stage-1 weights: {differ[0]} has another shape than this run's network's")
    last = _last_linear(qnet)
    out = dict(theirs)
    for prefix in {k.rsplit(".", 1)[0] for k in differ}:
        w, b = f"{prefix}.weight", f"{prefix}.bias"
        if not prefix.endswith(f"{BASE}{last}") or w not in differ or b not in differ:
            raise CheckpointError(f"stage-1 weights: {differ[0]} has another shape than this run's network's")
        out[w], out[b] = qnet.head_from_scalar(theirs[w], theirs[b])
        if tuple(out[w].shape) != tuple(ours[w].shape):
            raise CheckpointError(f"stage-1 weights: {w} does not convert to this run's "
                                  f"{tuple(ours[w].shape)}")
    log.info("stage-1 weights: the scalar output layer converted to %s's (%d atoms, a Gaussian of "
             "%.3g around each Q-value)", type(qnet).__name__, qnet.atoms, qnet.conversion_width())
    return out
