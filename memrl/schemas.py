"""Typed schemas of the top-level keys of every entry point, and their range checks.

Each ``conf/<command>.yaml`` extends its schema (``defaults: [<command>_schema, ...]``), so a
value of the wrong type fails at composition, naming the key. The values themselves live in
the YAML files (``MISSING`` here: the defaults have one place). Ranges and choices are
declared next to each field (:func:`spec`) and checked by :func:`check_fields`; the
``check_<command>`` functions add the checks of the groups and of the files a command reads.
All of it runs before Hydra makes the run folder (``memrl.hydra_callbacks.StartChecks``) and
again at the start of each typed function. Importing this module does not import torch.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from memrl.data.recipe import DemoRecipe
from memrl.dqn.config import PRECISIONS, UPDATE_MODES
from memrl.errors import UserError, config_error, load_run_config
from memrl.fields import SEED_MAX, _element_ok, _valid, check_fields, spec  # noqa: F401
from memrl.known_keys import check_known_keys


def check_writable(path: str | os.PathLike, key: str) -> None:
    """Refuse a folder that cannot be created or written, before anything is written there.

    Tries a probe file in the deepest existing ancestor (``os.access`` says yes to root even
    on a read-only mount, so it is not asked).
    """
    target = Path(path)
    probe_dir = target
    while not probe_dir.exists() and probe_dir != probe_dir.parent:
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        raise UserError(f"{target}: cannot be created ({probe_dir} is not a folder); "
                        f"set {key} to a writable folder")
    probe = probe_dir / f".memrl-write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise UserError(f"{target}: cannot write there ({probe_dir}: {err.strerror}); "
                        f"set {key} to a writable folder") from err


# ---------------------------------------------------------------------------------------------
# train


@dataclass
class TrainSchema:
    """``conf/train.yaml``: one training run (keys of the groups: their own schemas)."""

    task_name: str = MISSING
    """Name of the command's output folder (``outputs/<task_name>/...``)."""
    seed: int = spec(ge=0, le=SEED_MAX)
    """Seed of the run: weights, exploration, episode scenes."""
    seeds: list[int] | None = spec(ge=0, le=SEED_MAX, nonempty=True)
    """Several seeds of this configuration trained in one process, in turn
    (:func:`memrl.train.train_seeds`): run folders ``<output dir>/s<seed>``, each what that seed's
    own run writes (``seed`` is then not used); null: one run at ``seed``."""
    seeds_engine: str = spec(choices=("own", "shared"))
    """With ``seeds``: each seed's training envs on an engine of its own (``own``: the seeds take
    turns), or all seeds' on one batched engine of K x ``env.num_envs`` envs (``shared``: stepped
    together, :mod:`memrl.envs.shared_engine`; needs ``env.num_envs`` > 1 and no learned cars).
    The same episodes and weights either way."""
    device: str = MISSING
    """Where the network, loss, optimizer, replay storage and batched envs live: ``auto``
    (CUDA when present), ``cpu``, ``cuda`` or ``cuda:K``."""
    total_frames: int | None = spec(ge=1)
    """Env-step budget (null: no limit); checked at episode ends."""
    total_episodes: int | None = spec(ge=1)
    """Episode budget (null: no limit)."""
    log_every: int = spec(ge=1)
    """Updates between rows of ``updates.csv`` and logger points."""
    checkpoint_every: int = spec(ge=1)
    """Episodes between checkpoints."""
    progress: bool = MISSING
    """tqdm progress bar, drawn only on a terminal (else, as with false, a log line every
    ``log_every`` updates)."""
    resume: str | None = MISSING
    """A run folder to continue from its last checkpoint."""
    overwrite: bool = MISSING
    """A fresh start into a folder that holds a run (``hydra.run.dir=<run>``) replaces that run
    (its files are removed first); false: refused, one line (resume it, or pick another folder)."""
    variant: str | None = None
    """A label only: the ``study.variants`` name of this run, set by ``memrl.study`` (row label
    ``B (cue)``); null: none."""
    self_play_every: int = spec(ge=0)
    """Episodes between snapshots of the agent added to the learned cars' pool (0: off)."""
    debug: bool = MISSING
    """Full tracebacks for user errors (as ``HYDRA_FULL_ERROR=1``)."""
    env: Any = MISSING
    agent: Any = MISSING
    network: Any = MISSING
    """The Q-network (``network=table1|dueling``; :class:`memrl.modules.network_config.NetworkConfig`)."""
    buffer: Any = MISSING
    mode: Any = MISSING
    eval: Any = MISSING
    logger: Any = None
    paths: Any = MISSING


def _eval_node(cfg: DictConfig) -> None:
    from memrl.evaluation.periodic_config import PeriodicEvalConfig

    check_fields(PeriodicEvalConfig, cfg.eval, "eval.")


def check_env(node: Any, key: str = "env") -> None:
    """The env node, with the env's own validator (its message names ``env config '<key>'``);
    learned traffic loads :mod:`memrl.checkpoint`, which registers the learned cars with the env."""
    from memrl.envs.config import validate_env_config

    values = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else dict(node)
    validate_env_config(values)  # type: ignore[arg-type]
    if (values.get("opponent") or {}).get("type", "constant") != "constant":  # type: ignore[union-attr]
        import memrl.checkpoint  # noqa: F401 - registers the learned cars' controller with the env


def check_device(value: Any, key: str) -> None:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:K`` naming a device this machine has."""
    import re

    text = str(value)
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", text):
        raise config_error(key, f"expected auto, cpu, cuda or cuda:K, got {value!r}")
    if text.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise config_error(key, f"{text}: CUDA is not available on this machine "
                               "(use device=cpu, or device=auto to take CUDA where present)")
        index = int(text.split(":")[1]) if ":" in text else 0
        if index >= torch.cuda.device_count():
            raise config_error(key, f"{text}: only {torch.cuda.device_count()} CUDA device(s) here")


def check_train(cfg: DictConfig) -> None:
    """Every value of a train config, and the folders it names (resume, demos_path)."""
    from memrl.dqn.config import check_train_config
    from memrl.modules.network_config import check_network

    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(TrainSchema, cfg)
    check_env(cfg.env)  # before the relations of check_train_config read env keys
    check_train_config(cfg)
    check_network(cfg.network)
    from memrl.losses import td_term

    td_term(cfg.agent, cfg.network)  # the head's TD term takes this agent config (refusals name the key)
    from memrl.modules.risk import proposes

    if proposes(cfg.network) and cfg.agent.exploration == "boltzmann":
        raise config_error("network.task_action", "proposed needs the task head's own proposal, and "
                           "agent.exploration=boltzmann draws from the masked values (use another "
                           "exploration)")
    if cfg.self_play_every and cfg.env.opponent.type == "constant":
        raise config_error("self_play_every", "snapshots join the learned cars' pool; it needs "
                           "opponent=learned or opponent=mixed (or self_play_every=0)")
    _eval_node(cfg)
    if cfg.env.opponent.type != "constant":  # every pattern must match a past agent that saw these frames
        from memrl.checkpoint.opponents import check_pool_views, pool_views

        check_pool_views(pool_views([str(p) for p in cfg.env.opponent.pool]), cfg.env)
    check_device(cfg.device, "device")
    if cfg.get("variant") is not None and not re.fullmatch(VARIANT_NAME, str(cfg.variant)):
        raise config_error("variant", f"a label of letters, digits, '_', '.', '-' (as study.variants "
                           f"names), got {cfg.variant!r}")
    if cfg.resume is not None:
        check_resume(cfg)
    else:  # the start checks know Hydra's folder before Hydra makes it; train() checks its own
        from memrl.run_folder import check_new_run_folder, planned_run_dir

        if (folder := planned_run_dir(cfg)) is not None:
            check_new_run_folder(folder, bool(cfg.overwrite))
    from memrl.modes import mode_of

    mode = mode_of(cfg)
    demos = cfg.mode.demos_path if mode.needs_demos else None
    if mode.needs_demos and demos is not None and not Path(str(demos)).is_dir():
        raise config_error("mode.demos_path", f"no dataset folder {demos} (a folder made by "
                           "python -m memrl.record, or null for the scripted example)")
    if mode.needs_demos and demos is None:
        check_recipe(cfg.mode.get("example"), cfg.env, "mode.example")
    # the offline stage's settings (mode B's stage1), where the mode has one
    offline = [s.settings for s in mode.stages if s.offline]
    init = cfg.mode[offline[0]].get("init") if offline else None
    if init is not None:
        from memrl.checkpoint import CheckpointError, stage1_source
        from memrl.modules.qnet import network_for_task

        try:
            stage1_source(str(init), cfg.env, network_for_task(cfg.network, cfg.env, float(cfg.agent.gamma)))
        except CheckpointError as e:
            raise config_error(f"mode.{offline[0]}.init", str(e)) from None


def check_resume(cfg: DictConfig) -> None:
    """``resume`` names a run folder with a complete checkpoint, intact (its manifest) and made
    under this config: checked before Hydra writes into the folder, so a refused resume leaves
    nothing there (and ``resume=<any folder>`` writes nothing into a folder that is no run)."""
    from memrl.checkpoint import resume as ckpt

    run = Path(cfg.resume)
    if not run.is_dir():
        raise config_error("resume", f"no run folder {cfg.resume}")
    if not (run / "config.yaml").is_file() and not (run / "checkpoints").is_dir():
        raise config_error("resume", f"{run} is not a run folder (no config.yaml, no checkpoints/)")
    if (run / "config.yaml").is_file():
        load_run_config(run / "config.yaml")
    state = ckpt.load_state(ckpt.find(run), cfg)
    from memrl.modes import mode_of

    offline = [s.name for s in mode_of(cfg).stages if s.offline]
    if offline and state["counters"]["stage"] not in offline:  # past its offline stage: from its weights
        from memrl.checkpoint import OFFLINE_WEIGHTS, check_stage1

        check_stage1(run / "checkpoints" / OFFLINE_WEIGHTS)


def check_recipe(recipe: Any, env: Any, key: str) -> None:
    """A demo recipe's values, and the env its episodes are recorded in."""
    import inspect

    from memrl.data.recipe import recipe_error, recipe_values
    from memrl.envs.config import EnvConfigError
    from memrl.modules.scripted import ScriptedDriver

    if (bad := recipe_error(recipe)) is not None:
        raise config_error(f"{key}.{bad[0]}", bad[1])
    known = set(inspect.signature(ScriptedDriver).parameters)
    for name in recipe_values(recipe)["driver"]:
        if name not in known:
            raise config_error(f"{key}.driver.{name}", "not a ScriptedDriver option "
                               f"(conf/demos/scripted.yaml lists them: {', '.join(sorted(known))})")
    env_values = OmegaConf.to_container(env, resolve=True) if isinstance(env, DictConfig) else dict(env)
    try:
        check_env({**env_values, **recipe_values(recipe)["env"]})  # type: ignore[dict-item]
    except EnvConfigError as e:
        raise config_error(f"{key}.env", str(e)) from None


# ---------------------------------------------------------------------------------------------
# record


@dataclass
class RecordSchema:
    """``conf/record.yaml``: record prior-knowledge datasets."""

    task_name: str = MISSING
    episodes: int = spec(ge=1)
    """Episodes to record."""
    seed: int = spec(ge=0, le=SEED_MAX)
    """Episode i is reset with seed + i."""
    keep: str = spec(choices=("stable", "all"))
    """stable: only episodes with no collision that reached the target lane | all."""
    tail_steps: int | None = spec(ge=0)
    """Steps kept after the target lane is reached (null: whole episodes)."""
    action_noise: float = spec(ge=0.0, lt=1.0)
    """Probability per step of a random action instead of the driver's."""
    out: str = MISSING
    """Dataset folder."""
    resume: str | None = None
    """Folder of a stopped recording to go on with (its plan replaces episodes, seed, keep, ...)."""
    overwrite: bool = MISSING
    example: bool = MISSING
    recipe: DemoRecipe = field(default_factory=DemoRecipe)
    """``example=true``: how the example is recorded (training's ``mode.example``, whose
    defaults these are; e.g. recipe.episodes=12 for the smoke preset's)."""
    progress: bool = MISSING
    debug: bool = MISSING
    env: Any = MISSING
    demos: Any = MISSING
    paths: Any = MISSING


def check_record(cfg: DictConfig) -> None:
    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(RecordSchema, cfg)
    check_env(cfg.env)
    if cfg.example:
        for key, default in (("episodes", 10), ("seed", 0), ("tail_steps", None), ("action_noise", 0.0)):
            if cfg[key] != default:
                raise config_error("example", f"example=true records `recipe` (training's "
                                   f"mode.example); set recipe.{key}, not {key}")
        check_recipe(cfg.recipe, cfg.env, "recipe")
        if cfg.demos.source != "scripted":
            raise config_error("example", "the example dataset is made by the scripted driver "
                               f"(demos=scripted), not demos={cfg.demos.source}")
        check_writable(cfg.paths.data_dir, "paths.data_dir")
    elif cfg.get("resume") is not None:
        check_writable(Path(str(cfg.resume)), "resume")
    else:
        out = Path(str(cfg.out))
        if out.exists() and not cfg.overwrite:
            raise config_error("out", f"{out} exists; set overwrite=true or another out=")
        check_writable(out.parent, "out")


# ---------------------------------------------------------------------------------------------
# evaluate


@dataclass
class EvaluateSchema:
    """``conf/evaluate.yaml``: Table III protocol on one or more policies."""

    task_name: str = MISSING
    workers: int = spec(ge=0)
    """Processes (0: one per CPU)."""
    batch: int = spec(ge=1)
    """Episodes stepped in lockstep per process."""
    progress: bool = MISSING
    debug: bool = MISSING
    resume: str | None = None
    """Folder of a stopped evaluation (a person's): drive its missing episodes (same scenes)."""
    overwrite: bool = MISSING
    """Replace a run's evaluation made under another protocol (false: refuse)."""
    env: Any = MISSING
    protocol: Any = MISSING
    policy: Any = MISSING
    paths: Any = MISSING


def check_evaluate(cfg: DictConfig) -> None:
    from memrl.evaluation.protocol import check_protocol

    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(EvaluateSchema, cfg)
    check_env(cfg.env)
    check_protocol(cfg.protocol)
    if OmegaConf.is_missing(cfg.policy, "run") if "run" in cfg.policy.keys() else False:
        raise config_error("policy.run", "missing: give policy.run=<run or multirun folder>, "
                           "or another policy (policy=scripted|random|human)")
    for key in cfg.policy.keys():  # the other policies' mandatory keys (policy=python: target)
        if OmegaConf.is_missing(cfg.policy, key):
            raise config_error(f"policy.{key}", f"missing: give policy.{key}=... (conf/policy/)")
    run = cfg.policy.get("run") if "run" in cfg.policy.keys() else None
    runs = [] if run is None else ([run] if isinstance(run, str) else list(run))
    for item in runs:
        if not Path(str(item)).exists():
            raise config_error("policy.run", f"no such folder {item} (a training run or multirun folder)")


# ---------------------------------------------------------------------------------------------
# report


@dataclass
class RolloutsSchema:
    """Fig. 7 picture strips and videos."""

    rows: list[str] = MISSING
    unit: str | None = MISSING
    initial_lane: str = spec(choices=("random", "non_goal"))
    count: int = spec(ge=1)
    pick: str = spec(choices=("success", "first"))
    steps: list[int] | None = spec(ge=0)
    scale: float = spec(gt=0)
    video: bool = MISSING
    fps: float = spec(gt=0)
    crashes: int = spec(ge=0)
    """Crashed episodes per kind replayed into ``crashes_<row>_<kind>.png`` (0: none)."""
    crash_frames: int = spec(ge=1)
    """Steps shown up to each crash."""


@dataclass
class ReportSchema:
    """``conf/report.yaml``: Table III, Fig. 5 and Fig. 7 from evaluations."""

    task_name: str = MISSING
    runs: list[str] = spec(nonempty=True)
    """Folders to search (eval.json, episodes.csv + config.yaml below them)."""
    evaluate_missing: bool = MISSING
    overwrite: bool = MISSING
    """Let evaluate_missing replace a run's evaluation made under another protocol (false: refuse)."""
    workers: int = spec(ge=0)
    batch: int = spec(ge=1)
    progress: bool = MISSING
    confidence: float = spec(gt=0.0, lt=1.0)
    n_resamples: int = spec(ge=1)
    bootstrap_seed: int = spec(ge=0, le=SEED_MAX)
    comparisons: list[list[str]] = MISSING
    """Pairs [a, b] of Table III rows."""
    row_ignore: list[str] = MISSING
    """Run config keys (and prefixes) that never split a Table III row."""
    fig5: bool = MISSING
    train_runs: list[str] | None = None
    """Folders of the training runs whose curves Fig. 5 draws (None: those below ``runs``)."""
    smooth: int = spec(ge=1)
    curve_resamples: int = spec(ge=1)
    rollouts: RolloutsSchema = field(default_factory=RolloutsSchema)
    debug: bool = MISSING
    protocol: Any = MISSING
    paths: Any = MISSING


def check_report(cfg: DictConfig) -> None:
    from memrl.evaluation.protocol import check_protocol

    if not cfg.runs:
        raise config_error("runs", "give one or more run, multirun or evaluation folders, "
                           "e.g. runs=[outputs/train/multiruns/2026-11-22_10-00-00]")
    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(ReportSchema, cfg)
    check_protocol(cfg.protocol)
    duration = int(cfg.protocol.duration)
    if int(cfg.rollouts.crash_frames) > duration:
        raise config_error("rollouts.crash_frames", f"{cfg.rollouts.crash_frames} steps before a crash "
                           f"is a window longer than an episode (protocol.duration={duration})")
    for pair in cfg.comparisons:
        if len(pair) != 2:
            raise config_error("comparisons", f"expected pairs [a, b] of row labels, got {list(pair)}")
    for key in cfg.row_ignore:
        if not str(key).strip() or " " in str(key):
            raise config_error("row_ignore", f"expected config keys such as paths or log_every, got {key!r}")
    for item in cfg.get("train_runs") or []:
        if not Path(str(item)).exists():
            raise config_error("train_runs", f"no such folder {item}")
    for item in cfg.runs:
        if not Path(str(item)).exists():
            raise config_error("runs", f"no such folder {item}")
        folder = Path(str(item))
        if not cfg.evaluate_missing and not (folder / "eval.json").is_file() and \
                next(folder.glob("**/eval.json"), None) is None:
            raise config_error("runs", f"{item}: no evaluation (eval.json) there; run python -m "
                               "memrl.evaluate first or set evaluate_missing=true")


# ---------------------------------------------------------------------------------------------
# deploy


@dataclass
class DeploySchema:
    """``conf/deploy.yaml``: the agent through PID control of a simulated car."""

    task_name: str = MISSING
    debug: bool = MISSING
    env: Any = MISSING
    deploy: Any = MISSING
    paths: Any = MISSING


def check_deploy(cfg: DictConfig) -> None:
    from memrl.control.config import DeployConfig, check_deploy_config

    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(DeploySchema, cfg)
    check_env(cfg.env)
    merged = OmegaConf.merge(OmegaConf.structured(DeployConfig), cfg.deploy)
    dcfg = check_deploy_config(OmegaConf.to_object(merged))  # type: ignore[arg-type]
    if dcfg.policy == "checkpoint" and not Path(str(dcfg.checkpoint)).exists():
        raise config_error("deploy.checkpoint", f"no such file or run folder {dcfg.checkpoint}")


# ---------------------------------------------------------------------------------------------
# bench

BENCHMARK_NAMES = ("env", "opponents", "batched", "learner", "memory", "e2e", "stage1", "eval", "pool",
                   "seeds", "group")


@dataclass
class EnvBench:
    steps: int = spec(ge=1)
    vehicles_count: int = spec(ge=0)
    seed: int = spec(ge=0, le=SEED_MAX)
    torchrl: bool = MISSING


@dataclass
class OpponentsBench:
    steps: int = spec(ge=1)
    vehicles_count: int = spec(ge=1)
    seed: int = spec(ge=0, le=SEED_MAX)


@dataclass
class LearnerBench:
    batch_sizes: list[int] = spec(ge=1, nonempty=True)
    seconds: float = spec(gt=0)
    rounds: int = spec(ge=1)
    warmup_updates: int = spec(ge=0)
    buffer_transitions: int = spec(ge=1)
    ablation: bool = MISSING
    seed: int = spec(ge=0, le=SEED_MAX)
    learning: bool = True
    """At the first batch size, memrl with each learning option (n-step, shifts, heads) on."""


@dataclass
class MemoryBench:
    transitions: int = spec(ge=1)
    naive: bool = MISSING
    seed: int = spec(ge=0, le=SEED_MAX)
    timeout_s: float = spec(gt=0)
    limit_gb: float = spec(gt=0)


@dataclass
class E2EBench:
    total_frames: int = spec(ge=1)
    overlap: list[bool] = MISSING
    num_envs: list[int] = spec(ge=1, nonempty=True)
    gpu_num_envs: list[int] = spec(ge=1)
    gpu_batch_sizes: list[int] = spec(ge=1)
    gpu_total_frames: int = spec(ge=1)
    update_modes: list[str] = spec(choices=UPDATE_MODES, nonempty=True)
    gpu_update_modes: list[str] = spec(choices=UPDATE_MODES, nonempty=True)
    device: str = MISSING
    learner_seconds: float = spec(gt=0)
    seed: int = spec(ge=0, le=SEED_MAX)
    overrides: list[str] = MISSING


@dataclass
class SeedsBench:
    seeds: list[int] = spec(ge=1, nonempty=True)
    batch_size: int = spec(ge=1)
    seconds: float = spec(gt=0)
    rounds: int = spec(ge=1)
    precision: str = spec(choices=PRECISIONS)
    threads: int = spec(ge=0)
    device: str = MISSING
    lr: float = spec(gt=0)
    gamma: float = spec(gt=0, lt=1)
    grad_clip: float = spec(ge=0)
    seed: int = spec(ge=0, le=SEED_MAX)


@dataclass
class GroupBench:
    seeds: int = spec(ge=1)
    frames: int = spec(ge=1)
    rounds: int = spec(ge=1)
    overrides: list[str] = MISSING
    one_process_threads: int = spec(ge=0)
    engines: list[str] = spec(choices=("own", "shared"), nonempty=True)


@dataclass
class Stage1Bench:
    updates: int = spec(ge=1)
    variants: list[Any] = MISSING
    check_every: int = spec(ge=1)
    episodes: int = spec(ge=1)
    drive_every: int = spec(ge=0)
    data_dir: str | None = MISSING
    threads: int = spec(ge=0)


@dataclass
class BatchedBench:
    sizes: list[int] = spec(ge=1, nonempty=True)
    gpu_sizes: list[int] = spec(ge=1)
    seconds: float = spec(gt=0)
    reference_steps: int = spec(ge=1)
    vehicles_count: int = spec(ge=0)
    learned: bool = MISSING
    learned_sizes: list[int] = spec(ge=1)
    threads: int = spec(ge=1)
    device: str = MISSING
    seed: int = spec(ge=0, le=SEED_MAX)
    path_time: float = spec(ge=0, le=10)
    vec_sizes: list[int] = spec(ge=1)
    rounds: int = spec(ge=1)


@dataclass
class EvalBench:
    episodes: int = spec(ge=1)
    duration: int = spec(ge=1)
    vehicles_count: list[int] = spec(ge=0, nonempty=True)
    seed: int = spec(ge=0, le=SEED_MAX)
    net_seed: int = spec(ge=0, le=SEED_MAX)
    idle_bias: list[float] = spec(ge=0, nonempty=True)
    gym_batch: int = spec(ge=1)
    engine_batch: int | None = spec(ge=1)
    threads: int = spec(ge=1)
    device: str = MISSING
    checkpoints: int = spec(ge=0)


@dataclass
class PoolBench:
    cars: list[int] = spec(ge=1, nonempty=True)
    networks: int = spec(ge=1)
    seconds: float = spec(gt=0)
    rounds: int = spec(ge=1)
    threads: int = spec(ge=1)
    seed: int = spec(ge=0, le=SEED_MAX)


@dataclass
class BenchSchema:
    """``conf/bench.yaml``: side-by-side benchmarks."""

    task_name: str = MISSING
    benchmarks: list[str] = spec(choices=BENCHMARK_NAMES, nonempty=True)
    """Sub-benchmarks to run, in order."""
    env: EnvBench = field(default_factory=EnvBench)
    opponents: OpponentsBench = field(default_factory=OpponentsBench)
    batched: BatchedBench = field(default_factory=BatchedBench)
    learner: LearnerBench = field(default_factory=LearnerBench)
    memory: MemoryBench = field(default_factory=MemoryBench)
    e2e: E2EBench = field(default_factory=E2EBench)
    stage1: Stage1Bench = field(default_factory=Stage1Bench)
    eval: EvalBench = field(default_factory=EvalBench)
    pool: PoolBench = field(default_factory=PoolBench)
    seeds: SeedsBench = field(default_factory=SeedsBench)
    group: GroupBench = field(default_factory=GroupBench)
    debug: bool = MISSING
    paths: Any = MISSING


def check_bench(cfg: DictConfig) -> None:
    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(BenchSchema, cfg)


# ---------------------------------------------------------------------------------------------
# preview


@dataclass
class PreviewSchema:
    """``conf/preview.yaml``: PNGs of what the agent sees."""

    task_name: str = MISSING
    seed: int = spec(ge=0, le=SEED_MAX)
    driver: str = spec(choices=("idle", "random"))
    steps: list[int] = spec(ge=0, nonempty=True)
    scale: int = spec(ge=1)
    debug: bool = MISSING
    env: Any = MISSING
    paths: Any = MISSING


def check_preview(cfg: DictConfig) -> None:
    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(PreviewSchema, cfg)
    check_env(cfg.env)
    if max(int(x) for x in cfg.steps) > int(cfg.env.duration):
        raise config_error("steps", f"{list(cfg.steps)}: a step after the episode's end "
                           f"(env.duration={cfg.env.duration}) shows nothing")


# ---------------------------------------------------------------------------------------------
# study

class ModeLabels:
    """The Table III labels of every declared mode (:data:`memrl.modes.MODES`), read each time
    they are checked: a mode registered after this module was imported (a test's toy mode, a
    user's module) is a valid ``study.modes`` value too."""

    def __iter__(self) -> Any:
        from memrl.modes import MODES

        return iter([m.label for m in MODES.values()])

    def __contains__(self, label: object) -> bool:
        return label in list(self)

    def __repr__(self) -> str:
        return repr(tuple(self))


STUDY_MODES = ModeLabels()
OPPONENTS = ("constant", "learned", "mixed")
BASELINES = ("scripted", "random")
GRID_KEYS = ("seed", "mode", "resume", "variant")
"""Train keys that the study's grid sets itself (``study.train_overrides`` may not)."""
VARIANT_NAME = r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}"
"""A name of ``study.variants``: part of run folder names (``cue_B_constant_s0``) and row labels."""


@dataclass
class StudyConfig:
    """``study`` node of ``conf/study.yaml``: the grid, where it goes and how it runs."""

    name: str = "table3"
    """Name of the study (its folder under ``outputs/study/``)."""
    dir: str = "${paths.output_root}/study/${study.name}"
    """The study folder: ``runs/``, ``baselines/``, ``stage1/``, ``report.md``, ``study.json``."""
    modes: list[str] = spec(["Default", "A", "B"], choices=STUDY_MODES, nonempty=True)
    """Training modes (rows of Table III)."""
    seeds: list[int] = spec([0, 1, 2, 3, 4], ge=0, le=SEED_MAX, nonempty=True)
    """Training seeds of every (mode, opponent)."""
    opponents: list[str] = spec([], choices=OPPONENTS)
    """Opponent groups to train among ([]: the train config's own, constant by default)."""
    baselines: list[str] = spec(["scripted", "random"], choices=BASELINES)
    """Untrained policies evaluated beside the runs."""
    train_overrides: list[str] = field(default_factory=list)
    """Overrides of every training run, e.g. [+experiment=smoke, total_frames=100000, device=cuda]."""
    variants: Any = None
    """Ablations: variant name -> train overrides added after ``train_overrides`` for its runs, e.g.
    {paths: ['env.bev.path_time=2'], plain: ['env.bev.path_time=0']}; the grid is then variants x
    modes x opponents x seeds, run folders ``<variant>_<mode>_<traffic>_s<seed>``, rows ``B (paths)``
    (null or {}: one grid with ``train_overrides`` only). Typed ``Any``: a typed dict node refuses
    new keys from the command line (Hydra's struct mode)."""
    report_overrides: list[str] = field(default_factory=list)
    """Overrides of the report config (``conf/report.yaml``), e.g. [n_resamples=2000]."""
    jobs: int = spec(1, ge=1)
    """Training processes at once (more than 1: spawned processes)."""
    seeds_per_process: int = spec(1, ge=1)
    """Seeds of one (variant, mode, opponent) trained in one process, their turns in order
    (:func:`memrl.train.train_group`): each run's folder, checkpoints and resume are its own
    single-seed run's. On the CPU a convenience (fewer processes, one import), not a speed-up."""
    workers: int = spec(2, ge=0)
    """Evaluation processes (0: one per CPU)."""
    batch: int = spec(8, ge=1)
    """Evaluation episodes stepped in lockstep per process."""
    stage1: bool = True
    """Also evaluate mode B's stage-1 weights (``checkpoints/stage1.pt``) on the protocol."""
    allow_changes: bool = False
    """Go on in a study folder made with other ``train_overrides`` or ``variants`` (finished runs
    are kept)."""
    progress: bool = True
    """Progress bars of the evaluations."""
    extend_from: str | None = None
    """An earlier study's folder whose finished runs this study continues to its bigger budget
    (``total_frames`` / ``total_episodes`` in ``train_overrides``; every other key the same):
    each run of this grid not started yet begins as a copy of the earlier run of its name and
    resumes from its last checkpoint (:mod:`memrl.studies.extend`). None: start from scratch."""
    train: bool = True
    """False: train nothing; evaluate and report the runs finished so far (an interim report
    of a study that trains in another process; the others are listed as not finished)."""
    evaluate: str = spec("each", choices=("each", "end", "none"))
    """When this call evaluates the trained runs on the protocol: ``each`` as each run finishes
    (a later interim report, ``study.train=false``, then reuses them), ``end`` after every run
    has trained, ``none`` not at all: train only, no report (e.g. on a GPU machine; the same
    command with ``study.train=false`` evaluates and reports them later, on any machine)."""
    status: bool = False
    """Only print where each run stands (finished, running, resumable, not started; env steps,
    updates, the checkpoint a resume continues from, evaluated or not): nothing is trained,
    evaluated or reported."""


@dataclass
class StudySchema:
    """``conf/study.yaml``: train, evaluate and report a grid of runs (Table III)."""

    task_name: str = "study"
    study: StudyConfig = field(default_factory=StudyConfig)
    debug: bool = False
    """Full tracebacks for user errors (as ``HYDRA_FULL_ERROR=1``)."""
    protocol: Any = MISSING
    paths: Any = MISSING


def override_key(override: str) -> str:
    """The config key an override names: ``+mode=A`` -> ``mode``, ``~x.y`` -> ``x.y``."""
    return override.split("=", 1)[0].lstrip("+~")


def check_study(cfg: DictConfig) -> None:
    """The study keys, the protocol and the study folder (the train overrides are checked when
    the grid's configs are composed)."""
    from memrl.evaluation.protocol import check_protocol

    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(StudySchema, cfg)
    check_protocol(cfg.protocol)
    s = cfg.study
    if s.evaluate == "none" and not s.train:
        raise config_error("study.evaluate", "none with study.train=false would neither train nor "
                           "evaluate; give study.evaluate=each to evaluate and report the finished runs")
    for key in ("modes", "seeds", "opponents", "baselines"):
        values = list(s[key])
        if len(set(values)) != len(values):
            raise config_error(f"study.{key}", f"a value appears twice in {values}")
    grid = GRID_KEYS + (("opponent",) if s.opponents else ())
    lists = [("study.train_overrides", s.train_overrides)]
    if s.variants is not None and not isinstance(s.variants, DictConfig | dict):
        raise config_error("study.variants", f"give a mapping of names to lists of train overrides, e.g. "
                           f"{{paths:['env.bev.path_time=2']}}, got {s.variants!r}")
    for key_, overrides in (s.variants or {}).items():
        name = str(key_)
        if not re.fullmatch(VARIANT_NAME, name):
            raise config_error("study.variants", f"variant name {name!r}: use letters, digits, '_', "
                               "'.' and '-' (up to 64, not starting with '.', '_' or '-'); it names run "
                               "folders")
        if not isinstance(overrides, ListConfig | list):
            raise config_error(f"study.variants.{name}", f"give a list of train overrides, got {overrides!r}")
        lists.append((f"study.variants.{name}", overrides))
    for where, overrides in lists:
        for o in overrides:
            key = override_key(str(o))
            if "=" not in str(o) or key in grid:
                raise config_error(where, f"{o!r}: give key=value overrides of the train config other "
                                   f"than {', '.join(grid)} (the grid sets those: study.modes, study.seeds, "
                                   "study.opponents, study.variants)")
    check_writable(str(s.dir), "study.dir")
    if s.extend_from is not None and Path(str(s.extend_from)).resolve() == Path(str(s.dir)).resolve():
        raise config_error("study.extend_from", f"{s.extend_from} is this study's own folder; give "
                           "the folder of the earlier study whose runs this one continues")


# ---------------------------------------------------------------------------------------------
# dagger


@dataclass
class DaggerSchema:
    """``conf/dagger.yaml``: DAgger with the scripted driver on call (:mod:`memrl.imitation.dagger`)."""

    task_name: str = MISSING
    seed: int = spec(ge=0, le=SEED_MAX)
    iterations: int = spec(ge=1)
    """DAgger iterations (0: the expert drives)."""
    steps_per_iteration: int = spec(ge=1)
    """Env steps per env and iteration."""
    beta: float = spec(ge=0.0, le=1.0)
    """Iterations >= 1: probability per step that the expert's action is taken."""
    epochs: int = spec(ge=1)
    batch_size: int = spec(ge=1)
    lr: float = spec(gt=0.0)
    mode: Any = MISSING
    progress: bool = MISSING
    debug: bool = MISSING
    env: Any = MISSING
    agent: Any = MISSING
    demos: Any = MISSING
    paths: Any = MISSING


def check_dagger(cfg: DictConfig) -> None:
    """Every value of a dagger config: its own keys, the env, the learner's and the expert's."""
    from memrl.dqn.config import AgentConfig

    check_known_keys(cfg)  # a key added with + that no schema has
    check_fields(DaggerSchema, cfg)
    check_fields(AgentConfig, cfg.agent, "agent.")
    if int(cfg.agent.threads) < 0:
        raise config_error("agent.threads", f"must be >= 0, got {cfg.agent.threads}")
    check_env(cfg.env)
    if cfg.demos.source != "scripted":
        raise config_error("demos", f"the expert reads the world state: demos=scripted, not "
                           f"demos={cfg.demos.source}")
    check_writable(str(cfg.paths.output_root), "paths.output_root")


SCHEMAS: dict[str, type] = {"train": TrainSchema, "record": RecordSchema, "evaluate": EvaluateSchema,
                            "report": ReportSchema, "deploy": DeploySchema, "bench": BenchSchema,
                            "preview": PreviewSchema, "study": StudySchema, "dagger": DaggerSchema}
"""Config name -> schema of its top-level keys (registered as ``<name>_schema``)."""

CHECKS: dict[str, Callable[[DictConfig], None]] = {
    "train": check_train, "record": check_record, "evaluate": check_evaluate,
    "report": check_report, "deploy": check_deploy, "bench": check_bench, "preview": check_preview,
    "study": check_study, "dagger": check_dagger}
"""Config name -> the check of everything that command reads."""
