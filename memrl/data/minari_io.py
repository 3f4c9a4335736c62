"""Minari (HDF5) export and import of prior-knowledge datasets (optional extra ``[minari]``).

A memrl dataset becomes a Minari dataset that d3rlpy, TorchRL's ``MinariExperienceReplay`` and
other offline-RL tools read: observations are the agent's stacked frames (uint8
``[stack, 84, 84]``, stored raw: Minari's default JPEG encoding is lossy), actions
``Discrete(9)``, rewards, terminations and truncations. A Minari episode is a run of consecutive
steps, so a recording whose stored steps skip some (``action_noise``, ``tail_steps``) gives one
Minari episode per run. memrl's metadata (env config, source, stats, ...) travels in the Minari
metadata under :data:`METADATA_KEY`, so :func:`import_minari` gives back the same transitions and
the same env-config hash. Minari keeps datasets under ``$MINARI_DATASETS_PATH`` (default
``~/.minari/datasets``).

From the shell::

    python -m memrl.data.minari_io export <memrl dataset folder> <minari id>
    python -m memrl.data.minari_io import <minari id> <memrl dataset folder> [--overwrite]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from memrl.data.demo_checks import DemoDatasetError, check_values
from memrl.data.demos import EnvCfg, load_demos, read_metadata, save_demos, transition_spec
from memrl.envs.vehicles import N_ACTIONS

METADATA_KEY = "memrl_metadata"
"""Minari metadata key holding memrl's ``metadata.json`` (as a JSON string)."""
FILLED_BY_SAVE = ("format_version", "env_config_hash", "spec", "created")
"""memrl metadata fields :func:`memrl.data.demos.save_demos` computes again on import."""


def _minari() -> Any:
    try:
        import minari
    except ImportError:
        raise ImportError("Minari export/import needs the optional extra: "
                          "pip install 'memrl[minari]'") from None
    return minari


def runs(td: TensorDictBase) -> list[slice]:
    """Runs of consecutive steps: a run ends at a done step, or where the next row's ``pixels``
    are not this row's ``("next", "pixels")``."""
    pixels, nxt = td.get("pixels"), td.get(("next", "pixels"))
    joined = (pixels[1:] == nxt[:-1]).flatten(1).all(1) & ~td.get(("next", "done"))[:-1].reshape(-1)
    starts = [0, *((~joined).nonzero().flatten() + 1).tolist(), len(td)]
    return [slice(a, b) for a, b in zip(starts[:-1], starts[1:], strict=True)]


def export_minari(path: str | os.PathLike, dataset_id: str, *, env_cfg: EnvCfg = None,
                  author: str | None = None, description: str | None = None) -> Any:
    """Write the memrl dataset at ``path`` as Minari dataset ``dataset_id`` (HDF5).

    Args:
        path: memrl dataset folder (any readable format version).
        dataset_id: Minari id, e.g. ``memrl/lane-change/scripted-v0``.
        env_cfg: when given, the dataset must match it (as :func:`load_demos`).
        author, description: Minari metadata.

    Returns:
        The ``minari.MinariDataset``.
    """
    minari = _minari()
    from gymnasium import spaces
    from minari.data_collector import EpisodeBuffer

    meta = read_metadata(path)
    td = load_demos(path, env_cfg)
    buffers = []
    for i, run in enumerate(runs(td)):
        part = td[run]
        flags = {k: part.get(("next", k)).reshape(-1).numpy() for k in ("terminated", "truncated")}
        buffers.append(EpisodeBuffer(
            id=i, observations=torch.cat([part.get("pixels"), part.get(("next", "pixels"))[-1:]]).numpy(),
            actions=part.get("action").numpy(), rewards=part.get(("next", "reward")).reshape(-1).numpy(),
            terminations=flags["terminated"], truncations=flags["truncated"]))
    shape = tuple(td.get("pixels").shape[1:])
    if description is None:
        description = (f"memrl prior knowledge ({meta.get('source', 'demos')}) for the lane-change task: "
                       f"observations are {shape[0]} stacked {shape[1]}x{shape[2]} grayscale BEV frames, "
                       f"actions the 9 (speed change x curvature change) indices")
    dataset = minari.create_dataset_from_buffers(
        dataset_id, buffers, observation_space=spaces.Box(0, 255, shape, np.uint8),
        action_space=spaces.Discrete(N_ACTIONS), algorithm_name=f"memrl {meta.get('source', 'demos')}",
        author=author, description=description,
        data_format="hdf5", jpeg_encoding=False)
    dataset.storage.update_metadata({METADATA_KEY: json.dumps(meta, default=str)})
    return dataset


def _episode_transitions(ep: Any) -> TensorDict:
    """One Minari episode as memrl transitions (``[T]``: T + 1 observations, T actions)."""
    obs = torch.from_numpy(np.asarray(ep.observations))
    flags = {k: torch.from_numpy(np.asarray(getattr(ep, k), dtype=bool)).reshape(-1, 1)
             for k in ("terminations", "truncations")}
    steps = len(flags["terminations"])
    return TensorDict({
        "pixels": obs[:-1], "action": torch.from_numpy(np.asarray(ep.actions)).long().reshape(steps),
        "is_demo": torch.ones(steps, dtype=torch.bool),
        "next": {"pixels": obs[1:],
                 "reward": torch.from_numpy(np.asarray(ep.rewards, dtype=np.float32)).reshape(-1, 1),
                 "terminated": flags["terminations"], "truncated": flags["truncations"],
                 "done": flags["terminations"] | flags["truncations"]},
    }, batch_size=[steps])


def _memrl_metadata(dataset: Any, env_cfg: EnvCfg) -> dict[str, Any]:
    stored = dataset.storage.metadata.get(METADATA_KEY)
    meta: dict[str, Any] = json.loads(stored) if stored else {"source": "minari"}
    for key in FILLED_BY_SAVE:
        meta.pop(key, None)
    if env_cfg is not None and "env_config" not in meta:
        from memrl.data.recording import env_config_values

        meta["env_config"] = env_config_values(env_cfg)
    if "env_config" not in meta:
        raise DemoDatasetError(f"{dataset.storage.data_path}: not exported by memrl; pass env_cfg "
                               "(the memrl env config its observations come from)")
    meta["counts"] = {k: v for k, v in dict(meta.get("counts", {})).items() if k != "frames"}
    meta["imported_from"] = {"minari": dataset.spec.dataset_id}
    return meta


def _check_spaces(dataset: Any, meta: Mapping[str, Any]) -> None:
    shape, _ = transition_spec(meta["env_config"], int(meta.get("frame_stack", 4)))["pixels"]
    obs, act = dataset.observation_space, dataset.action_space
    where = dataset.storage.data_path
    if tuple(getattr(obs, "shape", ()) or ()) != tuple(shape) or getattr(obs, "dtype", None) != np.uint8:
        raise DemoDatasetError(f"{where}: observation space {obs}, expected uint8 {tuple(shape)} "
                               "stacked frames")
    if getattr(act, "n", None) != N_ACTIONS:
        raise DemoDatasetError(f"{where}: action space {act}, expected Discrete({N_ACTIONS})")


def import_minari(dataset: str | Any, path: str | os.PathLike, *, env_cfg: EnvCfg = None,
                  overwrite: bool = False) -> Path:
    """Save a Minari dataset (an id or a ``MinariDataset``) as a memrl dataset at ``path``.

    Args:
        dataset: Minari id or dataset; observations must be the uint8 frame stacks of the env.
        path: memrl dataset folder to write.
        env_cfg: the memrl env config of the observations; needed only for datasets that memrl
            did not export (those carry their own).
        overwrite: replace an existing dataset at ``path``.

    Raises:
        DemoDatasetError: naming the Minari dataset's folder, for spaces or values memrl cannot use.
    """
    minari = _minari()
    if isinstance(dataset, str):
        dataset = minari.load_dataset(dataset)
    meta = _memrl_metadata(dataset, env_cfg)
    _check_spaces(dataset, meta)
    chunks = [_episode_transitions(ep) for ep in dataset.iterate_episodes()]
    where = dataset.storage.data_path
    check_values(torch.cat(chunks), lambda name: f"{where} ({name})")
    try:
        return save_demos(chunks, path, meta, overwrite=overwrite)
    except ValueError as e:  # e.g. observations that are not shifted frame stacks
        raise DemoDatasetError(f"{where}: {e}") from None


def main(argv: Sequence[str] | None = None) -> int:
    """``export``/``import`` from the shell; a bad dataset or a missing extra is one line on
    stderr and exit status 1."""
    parser = argparse.ArgumentParser(prog="python -m memrl.data.minari_io",
                                     description="Minari export/import of memrl demo datasets")
    sub = parser.add_subparsers(dest="command", required=True)
    exp = sub.add_parser("export", help="memrl dataset -> Minari dataset (HDF5)")
    exp.add_argument("dataset", help="memrl dataset folder")
    exp.add_argument("dataset_id", help="Minari id, e.g. memrl/lane-change/scripted-v0")
    imp = sub.add_parser("import", help="Minari dataset -> memrl dataset")
    imp.add_argument("dataset_id", help="Minari id (in $MINARI_DATASETS_PATH)")
    imp.add_argument("dataset", help="memrl dataset folder to write")
    imp.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    args = parser.parse_args(argv)
    # Minari's reminders to set author, e-mail, permalink, eval env: not errors, and not ours.
    warnings.filterwarnings("ignore", category=UserWarning, module="minari")
    try:
        if args.command == "export":
            out = export_minari(args.dataset, args.dataset_id)
            print(f"exported {out.total_steps} steps in {out.total_episodes} episodes to Minari "
                  f"dataset {args.dataset_id} ({out.storage.data_path})")
        else:
            path = import_minari(args.dataset_id, args.dataset, overwrite=args.overwrite)
            print(f"imported Minari dataset {args.dataset_id} into {path}")
    except (DemoDatasetError, ImportError, FileExistsError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
