"""A key that no schema has is refused by name, with or without ``+``, naming the nearest known
key; the ``+`` overrides the docs use (``+mode=B``, ``+experiment=smoke``) keep composing."""

from __future__ import annotations

import pytest

from memrl.errors import ConfigError, is_user_error, one_line
from memrl.known_keys import check_known_keys
from memrl.schemas import CHECKS

MISSPELT = [
    ("train", ["+agent.lrr=1"], "config 'agent.lrr': no such key (did you mean 'agent.lr'?)"),
    ("train", ["+mode=B", "+mode.stage1.lrr=1"],
     "config 'mode.stage1.lrr': no such key (did you mean 'mode.stage1.lr'?)"),
    ("train", ["+env.bev.widht=3"], "config 'env.bev.widht': no such key (did you mean 'env.bev.width'?)"),
    ("train", ["+seeed=1"], "config 'seeed': no such key (did you mean 'seed'?)"),
    ("train", ["+foo=bar"], "config 'foo': no such key (the keys here: agent, buffer,"),
    ("evaluate", ["+protocol.episodess=3"], "config 'protocol.episodess': no such key (did you mean"),
    ("record", ["+episdes=3"], "config 'episdes': no such key (did you mean 'episodes'?)"),
]


@pytest.mark.parametrize(("command", "overrides", "line"), MISSPELT,
                         ids=[" ".join(o) for _, o, _ in MISSPELT])
def test_a_key_added_with_plus_that_no_schema_has_is_refused(compose_cfg, command, overrides, line):
    cfg = compose_cfg(command, overrides)  # Hydra composes it ...
    with pytest.raises(ConfigError) as info:
        CHECKS[command](cfg)  # ... the command's check refuses it, before anything is written
    assert is_user_error(info.value) and one_line(info.value).startswith(line)
    assert "\n" not in one_line(info.value)


def test_hydras_own_refusal_without_plus_names_the_nearest_key(compose_cfg):
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException) as info:
        compose_cfg("train", ["agent.lrr=1"])
    assert one_line(info.value) == "config 'agent.lrr': no such key (did you mean 'agent.lr'?)"
    with pytest.raises(ConfigCompositionException) as info:  # another mode's key keeps its own line
        compose_cfg("train", ["mode.stage1.lr=1e-3"])
    assert one_line(info.value) == ("config 'mode.stage1.lr': mode default has no such key "
                                    "(mode B's key: add +mode=B)")


LEGITIMATE = [
    ("train", ["+mode=B"]), ("train", ["+mode=A"]), ("train", ["+experiment=smoke"]),
    ("train", ["+experiment=paper", "+mode=B"]), ("train", ["+mode=B", "+experiment=imitation"]),
    ("train", ["+experiment=smoke", "opponent=mixed", "network=dueling", "logger=tensorboard"]),
    ("record", ["+recipe.env.duration=30"]),  # an open dict node: its own check names it
    ("study", []), ("report", []), ("evaluate", []), ("deploy", []), ("bench", []),
    ("preview", []), ("dagger", []),
]


@pytest.mark.parametrize(("command", "overrides"), LEGITIMATE,
                         ids=[f"{c} {' '.join(o)}" for c, o in LEGITIMATE])
def test_the_documented_plus_overrides_hold_only_known_keys(compose_cfg, command, overrides):
    check_known_keys(compose_cfg(command, overrides))
