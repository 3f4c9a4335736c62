"""Mode R (RLPD's symmetric sampling): one declaration in memrl/modes.py and conf/mode/R.yaml;
half of every batch is prior knowledge from the first update, no offline stage, the margin
term optional; the study runs it as a row of its own."""

from __future__ import annotations

import pytest
import torch

from memrl.modes import MODES
from memrl.train import train
from tests.helpers import TINY, csv_rows


def test_mode_r_samples_half_demos_from_the_first_update_with_no_offline_stage(compose_cfg, tmp_path,
                                                                              demos):
    spec = MODES["R"]
    assert [s.name for s in spec.stages] == ["R"] and not spec.pretrains and spec.needs_demos
    cfg = compose_cfg("train", [*TINY, "+mode=R"])
    assert cfg.mode.demo_fraction == 0.5 and cfg.mode.margin_weight == 0
    assert cfg.mode.example.episodes == 12  # its smoke preset values, declared with the mode
    summary = train(cfg, tmp_path / "r", demos=demos)
    assert summary.stage == "R" and summary.updates > 0
    rows = csv_rows(tmp_path / "r" / "updates.csv")
    # exactly round(0.5 x 8) = 4 demos in every batch, from the first logged update on
    assert rows and {(r["demo_count_min"], r["demo_count_max"]) for r in rows} == {("4", "4")}
    assert not (tmp_path / "r" / "checkpoints" / "stage1.pt").exists()


def test_mode_r_builds_the_margin_term_only_when_asked(compose_cfg, demos):
    from memrl.dqn.builder import StageInputs, build_stage
    from memrl.losses import MarginTerm, TDTerm

    for extra, terms in (([], (TDTerm(),)), (["mode.margin_weight=2", "mode.margin=0.5"],
                                             (TDTerm(), MarginTerm(2.0, 0.5)))):
        cfg = compose_cfg("train", [*TINY, "+mode=R", *extra])
        stage = build_stage(MODES["R"].stage("R"), StageInputs.of(cfg), demos, 1, torch.device("cpu"))
        assert stage.terms == terms


@pytest.mark.parametrize(("override", "message"), [
    ("mode.demo_fraction=1", "config 'mode.demo_fraction': must be in (0, 1), got 1"),
    ("mode.sampling=uniform", "config 'mode.sampling': must be one of stratified, proportional"),
    ("mode.margin_weight=-1", "config 'mode.margin_weight': must be >= 0, got -1"),
])
def test_bad_mode_r_values_are_refused_naming_the_key(compose_cfg, override, message):
    from memrl.errors import one_line
    from memrl.schemas import check_train

    with pytest.raises(ValueError) as info:
        check_train(compose_cfg("train", [*TINY, "+mode=R", override]))
    assert one_line(info.value).startswith(message), one_line(info.value)


def test_the_study_runs_mode_r_as_a_row_of_its_own(tmp_path):
    from hydra import compose, initialize_config_dir

    from memrl import CONF_DIR
    from memrl.configs import register_configs
    from memrl.study import study
    from tests.test_study import TRAIN, study_overrides

    folder = tmp_path / "s"
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("study", [*study_overrides(folder, TRAIN, modes="[R]", seeds="[0]"),
                                "study.baselines=[]"])
    result = study(cfg)
    assert sorted(result.trained) == ["R_constant_s0"]
    assert (folder / "runs" / "R_constant_s0" / "summary.json").is_file()
    table = [ln for ln in (folder / "report.md").read_text().splitlines() if ln.startswith("| R | 1 | ")]
    assert len(table) == 2  # Table III's row (n = 1 seed) and the joint survived-and-reached row
