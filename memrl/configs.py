"""Structured-config schemas registered with Hydra's ConfigStore (no torch import: ``--help`` stays fast)."""

from __future__ import annotations

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from memrl.control.config import DeployConfig
from memrl.dqn.config import AgentConfig, BufferConfig
from memrl.envs.config import LaneChangeConfig
from memrl.evaluation.periodic_config import PeriodicEvalConfig
from memrl.evaluation.protocol import ProtocolConfig
from memrl.modes import MODES
from memrl.modules.network_config import NetworkConfig
from memrl.schemas import SCHEMAS


def register_configs() -> None:
    """Register the typed schemas that the YAML groups extend, and memrl's resolvers
    (idempotent)."""
    # ${memrl.if_set:x,a,b}: a when x is set (not null or empty), else b (conf/hydra/train.yaml).
    OmegaConf.register_new_resolver("memrl.if_set", lambda x, a, b: a if x not in (None, "") else b,
                                    replace=True)
    cs = ConfigStore.instance()
    for name, schema in SCHEMAS.items():  # the top-level keys of each command
        cs.store(name=f"{name}_schema", node=schema)
    cs.store(group="env", name="lane_change_schema", node=LaneChangeConfig)
    cs.store(group="deploy", name="deploy_schema", node=DeployConfig)
    cs.store(group="agent", name="dqn_schema", node=AgentConfig)
    cs.store(group="buffer", name="buffer_schema", node=BufferConfig)
    cs.store(group="network", name="network_schema", node=NetworkConfig)
    # the same keys and defaults untyped, for a network with keys of its own (conf/network/c51.yaml):
    # its class's schema types and checks them (check_network)
    untyped = OmegaConf.to_container(OmegaConf.structured(NetworkConfig))
    cs.store(group="network", name="network_keys", node=untyped)
    cs.store(group="protocol", name="protocol_schema", node=ProtocolConfig)
    cs.store(group="eval_schema", name="base", node=PeriodicEvalConfig, package="eval")
    # Each mode's own typed `mode` node (memrl/modes.py): conf/train.yaml picks `default`,
    # conf/mode/<name>.yaml (`+mode=<name>`) overrides the choice with its own.
    for spec in MODES.values():
        cs.store(group="mode_schema", name=spec.name, node=spec.schema, package="mode")
        for preset, values in spec.presets.items():  # conf/train.yaml's optional mode_preset
            cs.store(group="mode_preset", name=f"{spec.name}_{preset}", node=values, package="mode")


def main(argv: list[str] | None = None) -> int:
    """``python -m memrl.configs --markdown``: print the configuration reference
    (``docs/configuration.md``, :mod:`memrl.config_reference`)."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if args != ["--markdown"]:
        print("usage: python -m memrl.configs --markdown > docs/configuration.md", file=sys.stderr)
        return 2
    from memrl.config_reference import markdown

    register_configs()
    sys.stdout.write(markdown())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
