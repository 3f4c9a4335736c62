"""How the scripted prior knowledge that modes A and B use by default is recorded.

A plain dataclass (omegaconf, no torch): the typed ``mode.example`` node of the training config and
the ``recipe`` of ``python -m memrl.record example=true``, and names the cached dataset.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from memrl.fields import SEED_MAX, spec

RECIPE_ENV_KEYS = ("initial_lane", "vehicles_count", "target_lane", "initial_speed",
                   "initial_offset", "initial_heading", "initial_curvature", "other_speed")
"""Env keys a recipe may change for recording: they pick which episodes are drawn, not what a
transition means, so the demos still fit the training env (``demos.EPISODE_KEYS``)."""


@dataclass
class DemoRecipe:
    """A dataset of the scripted driver (``memrl.modules.scripted.ScriptedDriver``).

    The defaults are the manoeuvre-focused recipe that made mode B's stage 1 change lanes
    (docs/results/stage1-slow-check.md): 240 episodes that start outside the target lane among 0-5
    cars, kept up to 30 steps after the target lane is reached (the wait for a gap, the change
    and the settling, not 250 steps of lane keeping), recorded with 20% random actions of which
    only the driver's own recoveries are stored (DART-style), from a driver that decides on
    positions (``merge_window``) and leaves small speed errors alone (``speed_tolerance``).
    """

    episodes: int = spec(240, ge=1)
    """Episodes recorded; only stable ones (no collision, target reached) are kept."""
    seed: int = spec(0, ge=0, le=SEED_MAX)
    """Episode i is reset with seed + i."""
    tail_steps: Any = 30
    """Steps kept after the target lane is reached (null: whole episodes)."""
    action_noise: float = spec(0.2, ge=0, lt=1)
    """Probability per step of a random action, not stored (0: none)."""
    driver: dict[str, Any] = field(
        default_factory=lambda: {"merge_window": 12.0, "speed_tolerance": 0.3})
    """ScriptedDriver keyword arguments (conf/demos/scripted.yaml documents each; null: its
    default)."""
    env: dict[str, Any] = field(
        default_factory=lambda: {"initial_lane": "non_goal", "vehicles_count": [0, 5]})
    """Env values used for recording only; keys from :data:`RECIPE_ENV_KEYS` (null: the
    training env's own)."""


LEGACY_RECIPE: dict[str, Any] = {"episodes": 10, "seed": 0, "tail_steps": None,
                                 "action_noise": 0.0, "driver": {}, "env": {}}
"""The example dataset before the recipe existed: 10 whole, noiseless episodes of the default
driver in the training env's own episodes (what a checkpoint without ``mode.example`` used)."""


def recipe_values(recipe: Any) -> dict[str, Any]:
    """A recipe (dataclass, DictConfig or mapping) as plain values, defaults filled in."""
    if isinstance(recipe, DemoRecipe):
        recipe = asdict(recipe)
    if recipe is None:
        recipe = {}
    if isinstance(recipe, DictConfig):
        recipe = OmegaConf.to_container(recipe, resolve=True)
    values = {**asdict(DemoRecipe()), **dict(recipe)}
    for part in ("driver", "env"):  # null: not set (the driver's default, the training env's own)
        values[part] = {str(k): v for k, v in dict(values[part] or {}).items() if v is not None}
    return values


def recipe_error(recipe: Any) -> tuple[str, str] | None:
    """(key, message) of the first bad value of a recipe, or None."""
    r = recipe_values(recipe)
    if not isinstance(r["episodes"], int) or r["episodes"] < 1:
        return "episodes", f"must be an int >= 1, got {r['episodes']!r}"
    if not isinstance(r["seed"], int) or r["seed"] < 0:
        return "seed", f"must be an int >= 0, got {r['seed']!r}"
    if r["tail_steps"] is not None and (not isinstance(r["tail_steps"], int) or r["tail_steps"] < 0):
        return "tail_steps", f"must be null or an int >= 0, got {r['tail_steps']!r}"
    if not 0.0 <= float(r["action_noise"]) < 1.0:
        return "action_noise", f"must be in [0, 1), got {r['action_noise']}"
    bad = sorted(set(r["env"]) - set(RECIPE_ENV_KEYS))
    if bad:
        return "env", (f"{bad[0]!r} would change what a transition means; a recipe may set only "
                       f"{', '.join(RECIPE_ENV_KEYS)}")
    return None


def recipe_hash(recipe: Any) -> str:
    """sha256 of the recipe's sorted JSON: part of the cached dataset's folder name."""
    text = json.dumps(recipe_values(recipe), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()
