"""Demo datasets: exact round trip, atomic writes, every corruption case, storage, example, CLI.

Format 1 (earlier versions), bad values and Minari: ``tests/test_demo_formats.py``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage

from memrl.data import demos as demos_mod
from memrl.data.demos import (
    FORMAT_VERSION,
    DemoDatasetError,
    dataset_bytes,
    demos_into_storage,
    env_config_hash,
    example_demos_path,
    load_demos,
    read_metadata,
    save_demos,
    transition_spec,
)
from memrl.data.recording import ensure_example_demos, reached_index, record_episodes, record_to_dataset
from memrl.data.transitions import TRANSITION_KEYS, to_transitions
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.envs.vehicles import action_index
from memrl.modules.policy import DrivingPolicy, PerturbedPolicy, PolicyModule
from memrl.modules.scripted import ScriptedDriver
from memrl.record import record
from memrl.train import prior_knowledge, train

SHORT = {"duration": 40, "vehicles_count": [0, 5]}  # short episodes keep the files small
BYTES_PER_TRANSITION = 5 * 8 + 8 + 1 + 4 + 3  # frame refs, action, is_demo, reward, 3 flags
FRAMES = 2 * (40 + 1)  # two 40-step episodes: the reset frame, then one new frame per step


def leaves(td: TensorDict) -> dict:
    return {k: td.get(k) for k in td.keys(include_nested=True, leaves_only=True)}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> tuple[Path, TensorDict]:
    """Two short scripted episodes recorded through the TorchRL env (all kept)."""
    path = tmp_path_factory.mktemp("demos") / "two"
    saved, rec = record_to_dataset(SHORT, ScriptedDriver(), path, episodes=2, seed=5,
                                   keep_stable=False, source="scripted")
    assert saved == path
    return path, torch.cat(rec.transitions)


@pytest.fixture
def copy(dataset, tmp_path) -> Path:
    """A private copy of the dataset to damage."""
    return Path(shutil.copytree(dataset[0], tmp_path / "copy"))


def test_layout_matches_the_shared_transition_keys():
    names = {tuple(k.split("/")) if "/" in k else k for k in transition_spec(None)}
    assert names == set(TRANSITION_KEYS)


def test_round_trip_is_exact(dataset):
    path, original = dataset
    loaded = load_demos(path, env_cfg=SHORT)
    assert loaded.batch_size == original.batch_size == (80,)
    a, b = leaves(original), leaves(loaded)
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
    assert loaded["is_demo"].all() and loaded["pixels"].dtype == torch.uint8
    meta = read_metadata(path)
    assert meta["format_version"] == FORMAT_VERSION == 2 and meta["source"] == "scripted"
    assert meta["counts"] == {"episodes": 2, "episodes_recorded": 2, "transitions": 80,
                              "frames": FRAMES}
    assert meta["env_config_hash"] == env_config_hash(SHORT) and meta["seed"] == 5
    assert meta["spec"]["pixels"] == {"shape": [4, 84, 84], "dtype": "uint8"}
    assert {"created", "stats", "episodes", "env_config"} <= meta.keys()


def test_recorded_pixels_are_exactly_what_the_env_gives(dataset):
    path, _ = dataset
    td = load_demos(path)
    env = make_env(SHORT)
    first = env.reset(seed=5)
    assert torch.equal(td["pixels"][0], first["pixels"])
    # within an episode, next pixels are the following step's pixels
    assert torch.equal(td["next", "pixels"][:39], td["pixels"][1:40])


def test_each_frame_is_stored_once(dataset):
    path, _ = dataset
    assert sorted(p.name for p in path.iterdir()) == ["frames.npz", "metadata.json", "transitions"]
    with np.load(path / "frames.npz") as npz:
        assert npz["pixels"].shape == (FRAMES, 84, 84) and npz["pixels"].dtype == np.uint8
    rows = dataset_bytes(path / "transitions")
    assert 80 * BYTES_PER_TRANSITION <= rows <= 80 * BYTES_PER_TRANSITION + 2_000  # + meta.json
    assert (path / "frames.npz").stat().st_size < FRAMES * 84 * 84  # deflated


def test_save_refuses_bad_layouts_and_existing_folders(dataset, tmp_path):
    path, original = dataset
    meta = {"env_config": SHORT}
    with pytest.raises(ValueError, match="keys"):
        save_demos(original.exclude("is_demo"), tmp_path / "a", meta)
    bad = original.clone()
    bad["action"] = bad["action"].to(torch.int32)
    with pytest.raises(ValueError, match="action"):
        save_demos(bad, tmp_path / "b", meta)
    with pytest.raises(ValueError, match="env_config"):
        save_demos(original, tmp_path / "c", {})
    with pytest.raises(FileExistsError):
        save_demos(original, path, meta)


def killed(*args, **kwargs):
    raise KeyboardInterrupt  # as if the recording were stopped before the metadata is written


def test_interrupted_save_leaves_nothing_that_looks_valid(dataset, tmp_path, monkeypatch):
    _, original = dataset
    target = tmp_path / "new"
    monkeypatch.setattr(demos_mod, "_write_metadata", killed)
    with pytest.raises(KeyboardInterrupt):
        save_demos(original, target, {"env_config": SHORT})
    assert not target.exists() and list(tmp_path.iterdir()) == []  # temporary folder removed


def test_killed_save_leaves_only_a_hidden_unloadable_folder(dataset, tmp_path, monkeypatch):
    _, original = dataset
    monkeypatch.setattr(demos_mod, "_write_metadata", killed)
    monkeypatch.setattr(demos_mod.shutil, "rmtree", lambda *a, **k: None)  # no clean-up: a kill
    with pytest.raises(KeyboardInterrupt):
        save_demos(original, tmp_path / "new", {"env_config": SHORT})
    monkeypatch.undo()
    (left,) = list(tmp_path.iterdir())
    assert left.name.startswith(".new.tmp-") and (left / "transitions").is_dir()
    with pytest.raises(DemoDatasetError, match="missing"):
        load_demos(left)


def test_interrupted_overwrite_keeps_the_old_dataset(copy, dataset, monkeypatch):
    _, original = dataset
    monkeypatch.setattr(demos_mod, "_write_metadata", killed)
    with pytest.raises(KeyboardInterrupt):
        save_demos(original[:10], copy, {"env_config": SHORT}, overwrite=True)
    monkeypatch.undo()
    assert load_demos(copy).shape == (80,)


def test_overwrite_swaps_in_the_new_dataset(copy, dataset):
    _, original = dataset
    save_demos(original[:10], copy, {"env_config": SHORT, "source": "again"}, overwrite=True)
    assert load_demos(copy).shape == (10,) and read_metadata(copy)["source"] == "again"
    assert [p.name for p in copy.parent.iterdir()] == ["copy"]  # no leftovers


def _edit_json(file: Path, edit) -> None:
    data = json.loads(file.read_text())
    edit(data)
    file.write_text(json.dumps(data))


CORRUPTIONS = {
    "truncated file": (lambda p: open(p / "transitions/next/reward.memmap", "r+b").truncate(100),
                       "transitions/next/reward.memmap", "truncated"),
    "truncated frames": (lambda p: open(p / "frames.npz", "r+b").truncate(1000),
                         "frames.npz", "unreadable frames"),
    "missing frames": (lambda p: (p / "frames.npz").unlink(), "frames.npz", "missing"),
    "missing tensor file": (lambda p: (p / "transitions/action.memmap").unlink(),
                            "transitions/action.memmap", "missing"),
    "altered shape": (lambda p: _edit_json(p / "transitions/meta.json",
                                           lambda d: d["frame_refs"].update(shape=[80, 4])),
                      "transitions/frame_refs.memmap", r"\[80, 4\]"),
    "wrong dtype": (lambda p: _edit_json(p / "transitions/meta.json",
                                         lambda d: d["action"].update(dtype="torch.int32")),
                    "transitions/action.memmap", "torch.int32"),
    "missing metadata": (lambda p: (p / "metadata.json").unlink(), "metadata.json", "missing"),
    "unreadable metadata": (lambda p: (p / "metadata.json").write_text("{not json"),
                            "metadata.json", "JSON"),
    "format version": (lambda p: _edit_json(p / "metadata.json", lambda d: d.update(format_version=3)),
                       "metadata.json", "format version 3"),
    "edited env config": (lambda p: _edit_json(p / "metadata.json",
                                               lambda d: d["env_config"].update(lane_width=3.5)),
                          "metadata.json", "does not match"),
    "wrong count": (lambda p: _edit_json(p / "metadata.json",
                                         lambda d: d["counts"].update(transitions=81)),
                    "transitions/", r"expected \[81"),
    "wrong frame count": (lambda p: _edit_json(p / "metadata.json",
                                               lambda d: d["counts"].update(frames=81)),
                          "frames.npz", r"expected \[81, 84, 84\]"),
    "not a dataset": (lambda p: shutil.rmtree(p), "copy", "no dataset folder"),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_each_corruption_gives_a_clear_error_naming_the_file(copy, case):
    damage, file, problem = CORRUPTIONS[case]
    damage(copy)
    with pytest.raises(DemoDatasetError, match=problem) as err:
        load_demos(copy)
    assert file in str(err.value)


def test_env_mismatch_names_the_differing_keys(dataset):
    path, _ = dataset
    with pytest.raises(DemoDatasetError, match="hash mismatch") as err:
        load_demos(path, env_cfg={**SHORT, "lane_width": 3.5, "bev": {"longitudinal_scale": 0.5}})
    message = str(err.value)
    assert "metadata.json" in message and "lane_width" in message and "bev" in message
    # episode-drawing keys do not matter: demos made from other starts still fit
    load_demos(path, env_cfg={**SHORT, "initial_lane": "non_goal", "vehicles_count": 5,
                              "initial_heading": 0.2, "initial_offset": 0.5})


def test_env_hash_is_stable_across_spellings():
    defaults = env_config_hash(None)
    assert env_config_hash({}) == defaults
    assert env_config_hash({"lane_width": 4}) == env_config_hash({"lane_width": 4.0}) == defaults
    assert env_config_hash(OmegaConf.create({"lanes_count": 2})) == defaults
    assert env_config_hash({"opponent": "constant", "initial_lane": "non_goal"}) == defaults
    assert env_config_hash({"reward": {"collision": -10.0}}) != defaults
    assert env_config_hash({"duration": 100}) != defaults
    assert len(defaults) == 64


@pytest.mark.parametrize("kind", ["tensor", "memmap"])
def test_demos_fill_a_torchrl_storage_once(dataset, tmp_path, kind):
    path, original = dataset
    td = load_demos(path)
    storage = (LazyTensorStorage(100) if kind == "tensor"
               else LazyMemmapStorage(100, scratch_dir=tmp_path / "scratch"))
    rows = demos_into_storage(td, storage, chunk=32)
    assert rows == slice(0, 80) and len(storage) == 80
    stored = storage.get(torch.arange(80))
    for key, value in leaves(original).items():
        assert torch.equal(stored.get(key), value), key
    stored_pixels = storage._storage["pixels"]
    assert stored_pixels.untyped_storage().data_ptr() != td["pixels"].untyped_storage().data_ptr()
    with pytest.raises(ValueError, match="do not fit"):
        demos_into_storage(td, LazyTensorStorage(50))


ONE_EPISODE = {"episodes": 1, "tail_steps": None, "action_noise": 0.0, "driver": {},
               "env": {"vehicles_count": 0, "initial_lane": "non_goal"}}
"""A recipe of one whole, noiseless episode on an empty road."""


def test_example_dataset_is_recorded_once_then_reused(tmp_path, monkeypatch):
    env = {"duration": 60}
    path = ensure_example_demos(env, tmp_path, ONE_EPISODE)
    assert path == example_demos_path(env, tmp_path, ONE_EPISODE) and path.parent == tmp_path
    assert path != example_demos_path(env, tmp_path, {**ONE_EPISODE, "seed": 1})  # one per recipe
    unset = {**ONE_EPISODE, "driver": {"merge_window": None}}  # null: the driver's default
    assert example_demos_path(env, tmp_path, unset) == path
    assert load_demos(path, env).shape == (60,)
    assert read_metadata(path)["stats"]["kept"]["goal"] == 1

    def no_recording(*args, **kwargs):
        raise AssertionError("the cached dataset should have been reused")

    import memrl.data.recording as recording
    monkeypatch.setattr(recording, "record_to_dataset", no_recording)
    assert ensure_example_demos(env, tmp_path, ONE_EPISODE) == path
    monkeypatch.undo()
    (path / "metadata.json").unlink()  # damaged cache: recorded again
    assert ensure_example_demos(env, tmp_path, ONE_EPISODE) == path
    assert load_demos(path, env).shape == (60,)


def test_example_follows_the_episodes_it_draws_and_is_recorded_among_constant_cars(tmp_path, monkeypatch):
    """The cache name covers the episode keys the recording draws with (two envs that draw other
    episodes do not share a dataset); the training traffic is not among them: the example is
    recorded among constant-speed cars, so a mixed-traffic run never loads the pool for it."""
    import memrl.data.recording as recording

    recipe = {**ONE_EPISODE, "env": {"vehicles_count": 2, "initial_lane": "non_goal"}}
    env = {"duration": 60}
    path = example_demos_path(env, tmp_path, recipe)
    assert example_demos_path({**env, "other_speed": [7.0, 9.0]}, tmp_path, recipe) != path
    assert example_demos_path({**env, "spawn_ahead": 80.0}, tmp_path, recipe) != path
    assert example_demos_path({**env, "vehicles_count": [0, 1]}, tmp_path, recipe) == path  # the recipe's own
    mixed = {**env, "opponent": {"type": "mixed", "pool": [str(tmp_path / "no_such_run")]}}
    assert example_demos_path(mixed, tmp_path, recipe) == path
    assert ensure_example_demos(mixed, tmp_path, recipe) == path  # no pool loaded: it does not exist
    recorded = read_metadata(path)["env_config"]
    assert recorded["opponent"]["type"] == "constant" and recorded["vehicles_count"] == 2

    def no_recording(*args, **kwargs):
        raise AssertionError("the constant-traffic run should reuse the same dataset")

    monkeypatch.setattr(recording, "record_to_dataset", no_recording)
    assert ensure_example_demos(env, tmp_path, recipe) == path


def test_example_dataset_asked_for_twice_at_once_is_recorded_once(tmp_path, monkeypatch):
    """A study's parallel jobs on an empty cache: the second caller waits on the first one's
    lock and loads its dataset instead of recording it again beside it."""
    import threading
    import time

    import memrl.data.recording as recording

    env = {"duration": 60}
    real, calls, inside = recording.record_recipe, [], threading.Event()

    def slow_record(*args, **kwargs):
        calls.append(threading.current_thread().name)
        inside.set()
        time.sleep(0.5)  # the second caller asks while the first is still recording
        return real(*args, **kwargs)

    monkeypatch.setattr(recording, "record_recipe", slow_record)
    paths = {}

    def ask(name):
        paths[name] = ensure_example_demos(env, tmp_path, ONE_EPISODE)

    first = threading.Thread(target=ask, args=("first",), name="first")
    second = threading.Thread(target=ask, args=("second",), name="second")
    first.start()
    assert inside.wait(timeout=60)
    second.start()
    first.join()
    second.join()
    assert calls == ["first"]
    assert paths["first"] == paths["second"] == example_demos_path(env, tmp_path, ONE_EPISODE)
    assert load_demos(paths["second"], env).shape == (60,)


def test_default_recipe_shows_lane_changes_from_non_goal_starts_with_recoveries(tmp_path):
    """The prior knowledge modes A and B use by default (4 of its 240 episodes here): every
    kept episode starts outside the target lane, changes lanes (steering actions, target
    reached), is cut 30 steps after reaching it, and was recorded with 20% random actions, of
    which only the driver's recoveries are stored (as
    ``test_record_action_noise_stores_only_the_drivers_own_steps`` checks)."""
    from dataclasses import asdict

    from memrl.data.recipe import DemoRecipe
    from memrl.envs.lane_change import LaneChangeEnv
    from memrl.envs.vehicles import ACTIONS

    recipe = {"episodes": 4}
    path = ensure_example_demos(None, tmp_path, recipe)
    meta = read_metadata(path)
    assert meta["recipe"] == {**asdict(DemoRecipe()), "episodes": 4}
    assert meta["action_noise"] == 0.2 and meta["tail_steps"] == 30
    assert meta["policy"]["merge_window"] == 12.0 and meta["policy"]["speed_tolerance"] == 0.3
    kept = meta["episodes"]
    assert len(kept) >= 3 and all(e["reached_target"] and not e["collided"] for e in kept)
    for e in kept:  # the recording env's own reset: started outside the target lane
        _, info = LaneChangeEnv(config=DemoRecipe().env).reset(seed=e["seed"])
        assert not info["on_target_lane"], e["seed"]
    assert all(e["perturbed"] > 0 for e in kept)  # random actions were taken in every episode
    demos = load_demos(path)
    steering = sum(ACTIONS[int(a)][1] != 0 for a in demos["action"])
    assert steering >= 2 * len(kept)  # at least into and out of the change, per episode
    # Rewards > 0 only once the car's centre is in the target lane (Table II: +1 there, -2 in
    # the other lane, +1 at the centre). Whole episodes would hold ~250 such steps each; cut 30
    # steps after the car is wholly in it (a few steps after its centre), far fewer.
    on_target = int((demos["next", "reward"] > 0).sum())
    assert len(kept) <= on_target < 50 * len(kept)
    assert int(demos["next", "terminated"].sum()) == 0  # cut ends bootstrap; none crashed


def test_record_command_prints_and_saves(compose_cfg, tmp_path, capsys):
    out = tmp_path / "rec"
    cfg = compose_cfg("record", ["episodes=2", "env.duration=40", "env.vehicles_count=[0,5]",
                                 "keep=all", f"out={out}", "progress=false"])
    summary = record(cfg)
    assert summary.path == out and summary.kept["transitions"] == 80 and summary.bytes > 0
    printed = capsys.readouterr().out
    assert "kept (all) 2 episodes, 80 transitions" in printed and "survival" in printed
    assert load_demos(out, cfg.env)["action"].shape == (80,)
    assert read_metadata(out)["policy"]["_target_"] == "memrl.modules.scripted.ScriptedDriver"


def test_record_stable_only_drops_unfinished_episodes(compose_cfg, tmp_path):
    # 10 steps are too few to reach the target lane from a non-goal start: nothing is kept
    cfg = compose_cfg("record", ["episodes=1", "env.duration=10", "env.initial_lane=non_goal",
                                 f"out={tmp_path / 'none'}", "progress=false"])
    summary = record(cfg)
    assert summary.path is None and summary.recorded["episodes"] == 1 and summary.kept["episodes"] == 0
    assert not (tmp_path / "none").exists()


def test_record_tail_steps_keeps_the_manoeuvre_and_a_fixed_tail(compose_cfg, tmp_path):
    """tail_steps=5: each kept episode is stored up to 5 steps after the step that reached
    the target lane (a prefix of the whole episode); it is still judged on the whole episode."""
    cfg = {"duration": 80, "vehicles_count": 0, "initial_lane": "non_goal"}
    whole = record_episodes(cfg, ScriptedDriver(), episodes=2, seed=7)
    cut = record_episodes(cfg, ScriptedDriver(), episodes=2, seed=7, tail_steps=5)
    assert whole.episodes == cut.episodes and whole.kept == cut.kept == [0, 1]
    env = make_env(cfg)
    for i, (full, part) in enumerate(zip(whole.transitions, cut.transitions, strict=True)):
        rollout = env.rollout(80, PolicyModule(ScriptedDriver(), unwrap(env)), auto_reset=False,
                              tensordict=env.reset(seed=7 + i), break_when_any_done=True)
        reached = reached_index(rollout)
        assert reached is not None and reached + 6 < len(full) == 80  # it went on after the tail
        assert len(part) == reached + 6
        assert (part == full[:reached + 6]).all()
        assert not part["next", "terminated"].any()  # the cut end bootstraps
    env.close()
    out = tmp_path / "tail"
    summary = record(compose_cfg("record", ["episodes=1", "env.duration=80", "env.vehicles_count=0",
                                            "env.initial_lane=non_goal", "tail_steps=5",
                                            f"out={out}", "progress=false"]))
    assert read_metadata(out)["tail_steps"] == 5 and len(load_demos(out)) < 80
    assert summary.kept["episodes"] == 1
    with pytest.raises(ValueError, match="tail_steps"):
        record(compose_cfg("record", ["tail_steps=-1", f"out={tmp_path / 'bad'}"]))


class _Keep(DrivingPolicy):
    """Always keeps speed and curvature: any other executed action is the recording noise."""

    def act(self, env, pixels):
        return action_index(0, 0)


def test_record_action_noise_stores_only_the_drivers_own_steps(compose_cfg, tmp_path):
    """action_noise=0.5: about half the steps execute a random action; exactly the steps
    whose executed action is the driver's are stored, in order, with their real pixels."""
    cfg = {"duration": 40, "vehicles_count": 0, "initial_lane": "non_goal"}
    rec = record_episodes(cfg, _Keep(), episodes=1, seed=3, keep_stable=False, action_noise=0.5)
    stored, stats = rec.transitions[0], rec.episodes[0]
    env = make_env(cfg)
    rollout = env.rollout(40, PolicyModule(PerturbedPolicy(_Keep(), 0.5, seed=3), unwrap(env)),
                          auto_reset=False, tensordict=env.reset(seed=3), break_when_any_done=True)
    env.close()
    own = rollout["action"] == action_index(0, 0)
    assert 5 < stats.perturbed == int((~own).sum()) < stats.steps - 5
    assert len(stored) == stats.steps - stats.perturbed
    assert (stored["action"] == action_index(0, 0)).all()
    assert (stored == to_transitions(rollout[own], is_demo=True)).all()
    out = tmp_path / "noisy"
    record(compose_cfg("record", ["episodes=1", "env.duration=40", "env.vehicles_count=0",
                                  "keep=all", "action_noise=0.25", f"out={out}", "progress=false"]))
    assert read_metadata(out)["action_noise"] == 0.25 and len(load_demos(out)) < 40
    for bad in ("1.0", "-0.1"):
        with pytest.raises(ValueError, match="action_noise"):
            record(compose_cfg("record", [f"action_noise={bad}", f"out={tmp_path / 'bad'}"]))


def test_record_example_and_bad_options(compose_cfg, tmp_path):
    base = ["env.duration=60", f"paths.data_dir={tmp_path}", "progress=false"]
    one = ["recipe.episodes=1", "recipe.tail_steps=null", "recipe.action_noise=0",
           "recipe.env.vehicles_count=0"]
    summary = record(compose_cfg("record", [*base, "example=true", *one]))
    recipe = compose_cfg("record", [*base, *one]).recipe
    assert summary.path == example_demos_path(compose_cfg("record", base).env, tmp_path, recipe)
    assert summary.kept["goal"] == 1 and summary.recorded["episodes"] == 1
    # what `python -m memrl.train +mode=B` would use with the same recipe: the same folder
    train_cfg = compose_cfg("train", ["+mode=B", "env.duration=60", f"paths.data_dir={tmp_path}",
                                      *(f"mode.example.{o.removeprefix('recipe.')}" for o in one)])
    assert len(prior_knowledge(train_cfg)) == len(load_demos(summary.path))
    with pytest.raises(ValueError, match="keep"):
        record(compose_cfg("record", [*base, "keep=some"]))
    with pytest.raises(ValueError, match="example"):
        record(compose_cfg("record", [*base, "example=true", "demos=human"]))
    for option, key in (("tail_steps=5", "tail_steps"), ("action_noise=0.1", "action_noise"),
                        ("episodes=3", "episodes")):
        with pytest.raises(ValueError, match=f"example.*set recipe.{key}, not {key}"):
            record(compose_cfg("record", [*base, "example=true", option]))
    with pytest.raises(ValueError, match=r"'recipe.env': .*'duration' would change"):
        record(compose_cfg("record", [*base, "example=true", "+recipe.env.duration=30"]))
    with pytest.raises(ValueError, match=r"'recipe.driver.merge_windows': not a ScriptedDriver"):
        record(compose_cfg("record", [*base, "example=true", "+recipe.driver.merge_windows=3"]))
    with pytest.raises(ValueError, match=r"'mode.example.env': env config 'initial_lane'"):
        train(compose_cfg("train", ["+mode=A", "mode.example.env.initial_lane=left",
                                    f"paths.data_dir={tmp_path}"]), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_dataset_recorded_before_a_later_key_still_loads(copy):
    """A dataset whose stored env config predates ``bev.path_length`` (the key is absent; as
    ``frame_stack``, ``frame_stride``, ``bev.path_time`` and ``shaping``)
    loads into the default env, keeps its hash, and is refused by an env that draws the path."""
    import hashlib

    meta_file = copy / "metadata.json"
    meta = json.loads(meta_file.read_text())
    assert meta["env_config"]["bev"].pop("path_length") == 0.0
    assert meta["env_config"].pop("frame_stack") == 1  # a later key too
    assert meta["env_config"].pop("frame_stride") == 1  # and another
    assert meta["env_config"]["bev"].pop("path_time") == 0.0  # and another
    assert meta["env_config"].pop("shaping") == {"weight": 0.0, "horizon": 3.0, "gamma": 0.95}
    # The hash as the version without the key computed it: over every stored key.
    old = demos_mod._canonical({k: v for k, v in meta["env_config"].items()
                                if k not in demos_mod.EPISODE_KEYS})
    text = json.dumps(old, sort_keys=True, separators=(",", ":"))
    meta["env_config_hash"] = hashlib.sha256(text.encode()).hexdigest()
    meta_file.write_text(json.dumps(meta))
    assert len(load_demos(copy, env_cfg=SHORT)) == len(load_demos(copy))
    with pytest.raises(DemoDatasetError, match="bev"):
        load_demos(copy, env_cfg={**SHORT, "bev": {"path_length": 20.0}})
    with pytest.raises(DemoDatasetError, match="bev"):
        load_demos(copy, env_cfg={**SHORT, "bev": {"path_time": 2.0}})
    with pytest.raises(DemoDatasetError, match="shaping"):  # shaped rewards are other transitions
        load_demos(copy, env_cfg={**SHORT, "shaping": {"weight": 1.0}})
