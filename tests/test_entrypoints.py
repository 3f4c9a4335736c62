"""The thin entry points, called as plain functions on the real composed configs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from memrl.bench import bench
from memrl.preview import preview


def test_preview_writes_non_blank_pngs(compose_cfg, tmp_path):
    cfg = compose_cfg("preview", ["steps=[0,5]", "driver=random"])
    files = preview(cfg, tmp_path)
    obs = cv2.imread(str(files.observations), cv2.IMREAD_GRAYSCALE)
    scene = cv2.imread(str(files.scene))
    assert obs.shape == (2 * (84 * 4 + 8), 4 * (84 * 4 + 8))
    assert obs.std() > 10 and scene.std() > 10


def test_preview_rejects_unknown_policy(compose_cfg, tmp_path):
    with pytest.raises(ValueError, match="driver"):
        preview(compose_cfg("preview", ["driver=fast"]), tmp_path)


def test_bench_env_measures_both_envs_and_writes_json(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["env.steps=30", "env.torchrl=true"])
    result = bench(cfg, tmp_path)
    env = result["env"]
    for key in ("memrl_gym_steps_per_s", "highway_fast_gym_steps_per_s",
                "memrl_torchrl_steps_per_s", "highway_fast_torchrl_steps_per_s"):
        assert env[key] > 0
    assert env["memrl_obs_shape"] == env["highway_fast_obs_shape"] == [4, 84, 84]
    assert json.loads((tmp_path / "bench.json").read_text())["env"]["steps"] == 30


def test_bench_batched_times_each_n_beside_the_reference_and_writes_json(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[batched]", "batched.sizes=[1,4]", "batched.seconds=0.05",
                                "batched.reference_steps=20", "batched.learned_sizes=[2]",
                                "batched.vec_sizes=[3]", "batched.rounds=3"])
    result = bench(cfg, tmp_path)["batched"]
    assert set(result["constant"]) == {"1", "4"} and set(result["learned"]) == {"2"}
    assert all(r > 0 for r in [*result["constant"].values(), *result["learned"].values()])
    ref = result["reference_gym_steps_per_s"]
    assert result["constant_ratio_to_reference"]["4"] == pytest.approx(result["constant"]["4"] / ref)
    assert set(result["path_time"]) == {"1", "4"} and all(r > 0 for r in result["path_time"].values())
    # each ratio's two rows side by side: 3 rounds, the ratio the median of the rounds' ratios
    # (the rows the medians of their own rounds, so their quotient may differ from it)
    assert result["rounds"] == 3
    for key in ("path_time_ratio_to_constant", "make_vec_ratio_to_reference",
                "make_vec_learned_ratio_to_reference"):
        rounds = result[f"{key}_rounds"]
        assert all(len(r) == 3 and min(r) > 0 for r in rounds.values())
        assert result[key] == {n: pytest.approx(float(np.median(r))) for n, r in rounds.items()}
    # gym.make_vec on the path_time frames beside the reference on the same frames, with learned cars too
    assert result["vec_frames"] == "bev.path_time=2.0, frame_stack=4"
    for rows, ref in (("make_vec", "reference_vec_frames_gym_steps_per_s"),
                      ("make_vec_learned", "reference_learned_vec_frames_gym_steps_per_s")):
        assert set(result[rows]) == set(result[ref]) == {"3"}
        assert result[rows]["3"] > 0 and result[ref]["3"] > 0
    assert result["device"] == "cpu" and result["torch_threads"] == 1
    assert json.loads((tmp_path / "bench.json").read_text())["batched"]["constant"] == result["constant"]


def test_bench_batched_rounds_of_one_give_the_rows_quotient(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[batched]", "batched.sizes=[2]", "batched.seconds=0.05",
                                "batched.reference_steps=20", "batched.learned=false",
                                "batched.vec_sizes=[2]", "batched.rounds=1"])
    result = bench(cfg, tmp_path)["batched"]
    assert result["path_time_ratio_to_constant"]["2"] == pytest.approx(
        result["path_time"]["2"] / result["constant"]["2"])
    assert result["make_vec_ratio_to_reference"]["2"] == pytest.approx(
        result["make_vec"]["2"] / result["reference_vec_frames_gym_steps_per_s"]["2"])


def test_bench_rejects_unknown_benchmark(compose_cfg, tmp_path):
    with pytest.raises(ValueError, match="benchmarks.*one of env"):
        bench(compose_cfg("bench", ["benchmarks=[nope]"]), tmp_path)


def test_bench_opponents_times_learned_and_constant_traffic(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[opponents]", "opponents.steps=10"])
    res = bench(cfg, tmp_path)["opponents"]
    assert res["learned_steps_per_s"] > 0 and res["constant_steps_per_s"] > 0


def test_bench_pool_times_the_grouped_forward_beside_vmap_and_both_agree(compose_cfg, tmp_path):
    cfg = compose_cfg("bench", ["benchmarks=[pool]", "pool.cars=[5]", "pool.networks=2", "pool.seconds=0.01",
                                "pool.rounds=1"])
    res = bench(cfg, tmp_path)["pool"]
    assert res["grouped_ms"]["5"] > 0 and res["vmap_ms"]["5"] > 0
    assert res["speedup"]["5"] == pytest.approx(res["vmap_ms"]["5"] / res["grouped_ms"]["5"])
    # the same float32 sums in other orders: far below the Q-values' own size (a car given
    # another network's row would differ by about that size)
    assert res["max_abs_q_difference"]["5"] <= 1e-3 * res["max_abs_q"]["5"]
    assert json.loads((tmp_path / "bench.json").read_text())["pool"]["networks"] == 2
