"""Exact state of the batched engine, for checkpoints taken while episodes are under way.

:func:`engine_state` gathers everything that determines the engine's future (car states,
flags, targets, policies, step counts, the frame ring, learned cars' frame stacks, and each
env's numpy generator); :func:`load_engine_state` puts it back into an engine built with the
same config, N and frame stack, on that engine's device. A resumed engine then gives exactly
the frames, rewards and flags the saved one would have given (``tests/test_batched_state.py``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from memrl.envs.config import BatchedEnvError, env_config_dict

if TYPE_CHECKING:
    from memrl.envs.batched import BatchedLaneChange

VERSION = 1
"""Layout of the state dict; bumped when its keys change."""
TENSORS = ("state", "present", "is_learned", "car_target", "policy", "target_lane", "steps", "crashed",
           "reached", "car_fresh")
"""Engine attributes saved as they are (``car_fresh`` is ``_car_fresh``)."""
LATER = {"frame_stride": 1, "bev.path_time": 0.0}
"""Keys (of the state and of its flattened config) added after version 1, with the value that
states saved before them had: such a state still loads into an engine at that value."""


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dict -> ``{"a.b": value}``."""
    out: dict[str, Any] = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _meta(engine: BatchedLaneChange, num_envs: int | None = None) -> dict[str, Any]:
    return {"num_envs": engine.num_envs if num_envs is None else num_envs, "frame_stack": engine.frame_stack,
            "frame_stride": engine.frame_stride,
            "car_slots": int(engine.present.shape[1]), "pool_size": engine.opponents.pool_size,
            "config": _flat(env_config_dict(engine.cfg))}


def _tensor(engine: BatchedLaneChange, name: str) -> torch.Tensor:
    return engine._car_fresh if name == "car_fresh" else getattr(engine, name)


def engine_state(engine: BatchedLaneChange, rows: slice | None = None, shift: int = 0) -> dict[str, Any]:
    """Everything that determines the engine's future, as copies (tensors on its device).

    ``rows`` (a ``slice(start, stop)`` of env indices): the state of an engine of those envs
    alone (:mod:`memrl.envs.shared_engine`), its frame ring turned by ``shift`` slots (the
    head its own engine would have: a slice loaded at another step keeps its own).
    """
    r = slice(None) if rows is None else rows
    n = engine.num_envs if rows is None else len(range(engine.num_envs)[r])
    state: dict[str, Any] = {"version": VERSION, **_meta(engine, n)}
    for name in TENSORS:
        state[name] = _tensor(engine, name)[r].clone()
    # [L, N, H, W] (L = history), newest in slot `head`
    state["frames"] = engine._frames[:, r].roll(shift, 0) if shift else engine._frames[:, r].clone()
    state["head"] = (engine._head + shift) % engine.history
    state["car_frames"] = None if engine._car_frames is None else engine._car_frames[r].clone()
    # each env's generator: the scene draws of its next resets and its learned cars' exploration
    state["rngs"] = [None if rng is None else rng.bit_generator.state for rng in engine.rngs[r]]
    return state


def _mismatch(engine: BatchedLaneChange, state: dict[str, Any], num_envs: int | None = None) -> list[str]:
    """What differs between the engine (of ``num_envs`` envs: a slice's) and the one that saved
    ``state`` (empty: nothing)."""
    mine = _meta(engine, num_envs)
    diffs = []
    if state.get("version") != VERSION:
        diffs.append(f"state layout version {state.get('version')!r} (this engine reads {VERSION})")
    for key in ("num_envs", "frame_stack", "frame_stride", "car_slots", "pool_size"):
        if state.get(key, LATER.get(key)) != mine[key]:
            diffs.append(f"{key}: saved {state.get(key, LATER.get(key))!r}, this engine {mine[key]!r}")
    saved = {**LATER, **state.get("config", {})}
    for key in sorted(set(saved) | set(mine["config"])):
        if saved.get(key, "<absent>") != mine["config"].get(key, "<absent>"):
            diffs.append(f"config {key}: saved {saved.get(key, '<absent>')!r}, "
                         f"this engine {mine['config'].get(key, '<absent>')!r}")
    return diffs


def load_engine_state(engine: BatchedLaneChange, state: dict[str, Any], rows: slice | None = None) -> int:
    """Restore ``state`` (from :func:`engine_state`) into ``engine``, on the engine's device; with
    ``rows``, into those envs only, the saved ring turned to the engine's head. Returns the
    shift that :func:`engine_state` takes to give the saved ring's head back (0 without rows).

    Raises:
        BatchedEnvError: the saving engine had another config, N, frame stack, car slots or
            pool size (the message lists every difference), or a part of the state is missing.
    """
    if not isinstance(state, dict):
        raise BatchedEnvError(f"engine state must be a dict from state_dict(), got {type(state).__name__}")
    r = slice(None) if rows is None else rows
    diffs = _mismatch(engine, state, None if rows is None else len(range(engine.num_envs)[r]))
    if diffs:
        raise BatchedEnvError("engine state was saved by a different engine: " + "; ".join(diffs))
    missing = [k for k in (*TENSORS, "frames", "head", "car_frames", "rngs") if k not in state]
    if missing:
        raise BatchedEnvError(f"engine state lacks {', '.join(missing)}")
    if (state["car_frames"] is None) != (engine._car_frames is None):
        raise BatchedEnvError("engine state: learned cars' frame stacks saved by an engine "
                              f"{'without' if state['car_frames'] is None else 'with'} learned cars")
    for name in TENSORS:
        _copy(_tensor(engine, name)[r], state[name], name)
    shift = 0
    if rows is None:
        _copy(engine._frames, state["frames"], "frames")  # in place: the ring's views stay valid
        engine._head = int(state["head"])
    else:  # the engine's head stays; the saved ring turns to it
        shift = (int(state["head"]) - engine._head) % engine.history
        frames = state["frames"]
        _copy(engine._frames[:, r], frames.roll(-shift, 0) if isinstance(frames, torch.Tensor) else frames,
              "frames")
    if engine._car_frames is not None:
        _copy(engine._car_frames[r], state["car_frames"], "car_frames")
    rngs = [None if s is None else _generator(s) for s in state["rngs"]]
    if len(rngs) != len(engine.rngs[r]):
        raise BatchedEnvError(f"engine state rngs: expected {len(engine.rngs[r])} generators, "
                              f"got {len(rngs)}")
    engine.rngs[r] = rngs
    return shift


def _copy(into: torch.Tensor, value: Any, name: str) -> None:
    if not isinstance(value, torch.Tensor) or value.shape != into.shape or value.dtype != into.dtype:
        got = (f"{tuple(value.shape)} {value.dtype}" if isinstance(value, torch.Tensor)
               else type(value).__name__)
        raise BatchedEnvError(f"engine state {name}: expected {tuple(into.shape)} {into.dtype}, got {got}")
    into.copy_(value.to(into.device))


def _generator(bit_state: dict[str, Any]) -> np.random.Generator:
    """A generator continuing from a saved ``bit_generator.state``."""
    bit_generator = getattr(np.random, bit_state["bit_generator"])()
    bit_generator.state = bit_state
    return np.random.Generator(bit_generator)
