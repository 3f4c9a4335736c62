from memrl.cli import normalize_argv


def test_multirun_flag_moves_to_the_front():
    assert normalize_argv(["+mode=B", "-m", "seed=0,1,2"]) == ["-m", "+mode=B", "seed=0,1,2"]
    assert normalize_argv(["seed=1", "--multirun"]) == ["--multirun", "seed=1"]
    assert normalize_argv(["seed=1"]) == ["seed=1"]


def test_bare_words_become_a_list_override():
    assert normalize_argv(["env", "learner", "env.steps=10"], "benchmarks") == [
        "env.steps=10", "benchmarks=[env,learner]"]
    assert normalize_argv(["--config-name", "other", "env"], "benchmarks") == [
        "--config-name", "other", "benchmarks=[env]"]
    assert normalize_argv(["env"]) == ["env"]  # no positional key: left for Hydra to judge
