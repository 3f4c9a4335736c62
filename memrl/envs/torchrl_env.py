"""The TorchRL pipeline: ``TransformedEnv`` over ``GymEnv`` giving stacked grayscale BEV pixels."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite, TensorSpec, Unbounded
from torchrl.envs import (
    CatFrames,
    Compose,
    GrayScale,
    ObservationTransform,
    RenameTransform,
    RewardSum,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.libs.gym import GymEnv, default_info_dict_reader

from memrl.envs import ENV_ID, register_envs
from memrl.envs.batched import INFO_KEYS, resolve_device
from memrl.envs.config import validate_env_config
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.stride import history_length


class EveryKthFrame(ObservationTransform):
    """Keeps every ``stride``-th frame along ``dim`` of a ``CatFrames`` stack, the newest (last)
    one included: ``CatFrames(N=(S-1)k+1)`` then this is the stack of S frames k steps apart.

    Args:
        stride: k >= 1 (1: the stack as it is).
        dim: the frame dimension (CatFrames' ``dim``).
        in_keys: the stacked keys.
    """

    def __init__(self, stride: int, dim: int = -3, in_keys: list[str] | None = None) -> None:
        keys = in_keys or ["pixels"]
        super().__init__(in_keys=keys, out_keys=list(keys))
        self.stride, self.dim = int(stride), dim

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        # counted from the newest frame: with CatFrames' N = (S-1)k+1 both ends are kept
        n = obs.shape[self.dim]
        index = torch.arange((n - 1) % self.stride, n, self.stride, device=obs.device)
        return obs.index_select(self.dim, index)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        for key in self.in_keys:
            spec = observation_spec[key]
            low, high = self._apply_transform(spec.space.low), self._apply_transform(spec.space.high)
            observation_spec[key] = Bounded(low, high, shape=low.shape, dtype=spec.dtype, device=spec.device)
        return observation_spec


def env_kwargs(env_cfg: Mapping[str, Any] | DictConfig | None) -> dict[str, Any]:
    """Plain, checked env config dict from a Hydra node or mapping (None: defaults)."""
    if env_cfg is None:
        return {}
    # Plain containers all the way down, also for a dict holding Hydra nodes.
    values: dict[str, Any] = {
        str(k): OmegaConf.to_container(v, resolve=True) if isinstance(v, DictConfig | ListConfig) else v
        for k, v in env_cfg.items()}
    validate_env_config(values)  # fail early, naming the key
    return values


def unwrap(env: TransformedEnv | GymEnv) -> LaneChangeEnv:
    """The :class:`LaneChangeEnv` inside a TorchRL env (to read or edit its world state)."""
    base = env.base_env if isinstance(env, TransformedEnv) else env
    return base._env.unwrapped  # type: ignore[union-attr]


def make_env(
    env_cfg: Mapping[str, Any] | DictConfig | None = None,
    *,
    frame_stack: int = 4,
    seed: int | None = None,
    render_mode: str | None = None,
    num_envs: int | None = None,
    device: Any = "cpu",
    engine: Any | None = None,
) -> TransformedEnv:
    """Build the lane-change env for TorchRL.

    Keys of the result: ``pixels`` uint8 ``[frame_stack, H, W]`` (grayscale frames, oldest
    first, ``env_cfg['frame_stride']`` steps apart: see :mod:`memrl.envs.stride`), ``action``
    (int64 index in [0, 9)), ``reward``, ``done``/``terminated``/``truncated``,
    ``step_count``, ``episode_reward`` and the flags of :data:`INFO_KEYS`.

    Args:
        env_cfg: lane-change config values (see :class:`memrl.envs.config.LaneChangeConfig`).
        frame_stack: number of frames concatenated along the channel dimension.
        seed: seed of the first reset (None: unseeded).
        render_mode: ``'rgb_array'`` to allow full-scene pictures via ``env.render()``.
        num_envs: None: one highway-env env (the reference); N: the batched engine with batch
            size ``[N]`` (:class:`~memrl.envs.torchrl_batched.BatchedLaneChangeEnv`), every key
            with a leading env dimension; env i's first reset takes ``seed + i``.
        device: the batched engine's device (``auto``, ``cpu``, ``cuda``, ``cuda:K``).
        engine: with ``num_envs``, the engine to step (a run's slice of a shared engine,
            :mod:`memrl.envs.shared_engine`) instead of a new one.
    """
    register_envs()
    values = {**env_kwargs(env_cfg), "frame_stack": 1}  # CatFrames / the engine's ring stack
    if num_envs is not None:
        if render_mode is not None:
            raise ValueError("render_mode: full-scene pictures come from the single env (num_envs=None)")
        from memrl.envs.torchrl_batched import BatchedLaneChangeEnv

        batched = TransformedEnv(BatchedLaneChangeEnv(values, num_envs, device, frame_stack, engine),
                                 Compose(StepCounter(), RewardSum()))
        if seed is not None:
            batched.set_seed(seed)
        return batched
    resolve_device(device)  # one env runs on the CPU, but a device that is none is refused alike
    base = GymEnv(ENV_ID, config=values, render_mode=render_mode, device="cpu",
                  categorical_action_encoding=True)
    spec = Composite({k: Unbounded(shape=(), dtype=torch.bool) for k in INFO_KEYS})
    base.set_info_dict_reader(default_info_dict_reader(list(INFO_KEYS), spec=spec))
    transforms = [RenameTransform(in_keys=["observation"], out_keys=["pixels"])]
    if base.observation_spec["observation"].shape[-3] == 3:  # env drew RGB (bev.grayscale=false)
        transforms.append(GrayScale(in_keys=["pixels"]))
    stride = validate_env_config(values).frame_stride
    # CatFrames has no stride: it keeps the (S-1)k+1 frames the stack spans, EveryKthFrame picks S
    transforms.append(CatFrames(N=history_length(frame_stack, stride), dim=-3, in_keys=["pixels"]))
    if stride > 1:
        transforms.append(EveryKthFrame(stride, dim=-3, in_keys=["pixels"]))
    transforms += [
        StepCounter(),
        RewardSum(),
    ]
    env = TransformedEnv(base, Compose(*transforms))
    if seed is not None:
        env.set_seed(seed)
    return env
