"""The configuration of a training run: one frozen dataclass per component, loaded from the
shipped YAML layers (the `layers/` folder of the installed `cluster.config` package, found through
importlib.resources), user files and `--set` overrides."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

from actors.envs.base import EnvError
from actors.envs.registry import get_spec
from actors.policy import ExplorationConfig
from buffer_service.config import DEFAULT_REPLAY_MAX_BYTES
from cluster.config.schema import (
    ConfigError,
    build,
    deep_merge,
    parse_overrides,
    read_yaml,
    to_dict,
)
from cluster.config.shipped import SHIPPED_RECIPE, default_files, recipe_file, recipe_name
from learner.precision import PRECISIONS
from learner.rdn import drop_retired_keys
from learner.registry import get_algo

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EnvConfig:
    """Which environment to train in.

    Attributes:
        id: registered env id, e.g. matrix/four_game (see `credit env list`), or the path
            of a skirmish map file (ending in .yaml or .yml), which trains as a skirmish map.
        args: keyword arguments of that env's factory (e.g. payoffs for matrix/four_game).
    """

    id: str = "matrix/four_game"
    args: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        get_spec(self.id)


@dataclass(frozen=True)
class ReplayConfig:
    """Episode replay of the value family (the dissertation: 1000 episodes / batch 32 on SMAC,
    200 / 4 on the matrix games).

    Attributes:
        capacity: episodes kept (oldest dropped).
        max_mib: byte budget of the episodes kept, per replay (one per seed), in MiB of
            their stored form (`buffer_service.packed`: about 3.2 KB per env step on
            bane_vs_bane); the oldest are dropped beyond it, whatever their count and length.
            The default (4 GiB) holds 5,000 bane_vs_bane episodes of its episode limit.
        batch_size: episodes per update.
        updates_per_episode: learner updates per inserted episode (the replay ratio; PyMARL's
            1: a batch of batch_size per new episode). The same in `--mode local` and
            `--mode cluster` for any number of actors and any run.num_envs: the buffer's
            sample-to-insert limiter enforces it in cluster mode.
        with_replacement: a batch may hold one episode twice (uniform with replacement) or
            not (PyMARL's sampling).
    """

    capacity: int = 1000
    max_mib: float = DEFAULT_REPLAY_MAX_BYTES / 2**20
    batch_size: int = 32
    updates_per_episode: float = 1.0
    with_replacement: bool = True

    def validate(self) -> None:
        if self.capacity < 1 or self.batch_size < 1:
            raise ValueError("capacity and batch_size must be >= 1")
        if not 0 < self.max_mib < 2**30:
            raise ValueError(f"max_mib must be a number of MiB > 0, got {self.max_mib}")
        if not self.updates_per_episode > 0:
            raise ValueError(f"updates_per_episode must be > 0, got {self.updates_per_episode}")
        if self.batch_size > self.capacity:
            raise ValueError(f"batch_size={self.batch_size} exceeds capacity={self.capacity}")


@dataclass(frozen=True)
class CyclingConfig:
    """EM-CAC's semi-online cycling buffer (the dissertation, 5.3.4: the last 32 episodes, 4
    new per training step). Each episode is sampled at most capacity / run.num_envs times.

    Attributes:
        capacity: episodes held; every policy-gradient step trains on all of them.
    """

    capacity: int = 32

    def validate(self) -> None:
        if self.capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {self.capacity}")


@dataclass(frozen=True)
class RunConfig:
    """The training loop.

    Attributes:
        t_max: env steps to train for.
        seed: base random seed.
        num_envs: envs stepped together per rollout round (episodes per update).
        test_interval: env steps between greedy evaluations.
        test_episodes: greedy episodes per evaluation.
        save_interval: env steps between checkpoints (0: only at the end).
        keep_best: after each greedy evaluation that scores at least the best so far (its
            win rate; its mean return on envs without a win), write the learner and the
            counters to `best/` beside the run's `checkpoint/`, with that evaluation in
            `best/best.json` (model selection on the training's own evaluations; judge the
            kept policy on fresh episodes, as `credit demo` does). Needs a run of one seed
            (n_ensemble = 1) that checkpoints.
        device: torch device of the learner ("cpu", "cuda", "cuda:1", ...). Rollout and
            evaluation workers always act on the CPU.
        acting_weights: what the learner process's own workers (local-mode rollouts, greedy
            evaluation) act with: "shared", the learner's agent module itself (CPU learners
            only); "copy", a CPU copy of it, refreshed from `learner.get_weights()` whenever
            the learner's version has moved on (what a cuda learner needs; on the CPU it acts
            exactly as "shared" does); "auto", shared on the CPU, a copy otherwise. Ray
            rollout actors always act on their own CPU copies.
        torch_threads: intra-op threads of the learner's torch (the agent and critic nets
            are small; more threads mostly spin against the actors for the same cores);
            0 = "auto": the CPUs this process may use less those other processes keep
            busy, at least 1, measured again every 10 s (`cluster.cpu`; a run whose thread
            count changes may differ from another in its last bits).
        keep_freed_memory: keep freed heap memory in the learner's process instead of
            returning it to the OS after every update (glibc only: `cluster.alloc`); 17-23%
            cheaper updates on maps with large batches, at the price of a resident size that
            stays at its peak (on bane_vs_bane with 3 seeds about 0.6 GiB more, a fixed cost;
            the replay is stored outside that heap and does not add to it).
        precision: "float32" or "bf16": the learner's matrix products in bfloat16 where the
            CPU (or GPU) has it, float32 otherwise (`learner.precision`; a different
            computation, so float32 stays the default until a learning comparison).
        max_policy_lag: drop sampled episodes more than this many versions behind the
            learner before an update, in both modes (0 = keep all; off-policy learners
            replay old episodes by design). Needs a run of one seed (n_ensemble = 1).
        loggers: where `credit train` logs each evaluation and the learner's losses
            (`cluster.metrics.run_loggers`): "jsonl" (metrics.jsonl, always on),
            "tensorboard" (event files in OUT/tensorboard/), "wandb" (Weights & Biases).
    """

    t_max: int = 2_000_000
    seed: int = 0
    num_envs: int = 1
    test_interval: int = 10_000
    test_episodes: int = 20
    save_interval: int = 0
    keep_best: bool = False
    device: str = "cpu"
    acting_weights: Literal["auto", "shared", "copy"] = "auto"
    torch_threads: int = 1
    keep_freed_memory: bool = True
    precision: Literal["float32", "bf16"] = "float32"
    max_policy_lag: int = 0
    loggers: tuple[Literal["jsonl", "tensorboard", "wandb"], ...] = ("jsonl",)

    def validate(self) -> None:
        try:
            device = torch.device(self.device)
        except RuntimeError as e:
            raise ValueError(f"device {self.device!r} is not a torch device ({e})") from None
        if self.acting_weights == "shared" and device.type != "cpu":
            raise ValueError(
                f"acting_weights=shared needs device=cpu (workers act on CPU tensors), got "
                f"device={self.device!r}; use acting_weights=copy or auto"
            )
        for name in ("t_max", "num_envs", "test_interval", "test_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.torch_threads < 0:
            raise ValueError(f"torch_threads must be >= 1, or 0 for auto, got {self.torch_threads}")
        if self.save_interval < 0:
            raise ValueError(f"save_interval must be >= 0, got {self.save_interval}")
        if self.max_policy_lag < 0:
            raise ValueError(f"max_policy_lag must be >= 0, got {self.max_policy_lag}")
        if "jsonl" not in self.loggers or len(set(self.loggers)) != len(self.loggers):
            raise ValueError(
                f"loggers must name jsonl (metrics.jsonl is the run's record) and each logger "
                f"once, got {list(self.loggers)}"
            )
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")


@dataclass(frozen=True)
class ClusterConfig:
    """The distributed runtime (`credit train --mode cluster`).

    Attributes:
        actors: rollout actors (Ray actors), each stepping run.num_envs envs.
        actor_cpus: CPUs Ray reserves per actor.
        publish_interval: learner updates between weight publications (one ray.put each).
        rate_slack: how many rounds of every actor may be in flight before inserts wait for
            the learner (the sample-to-insert limiter's error buffer, in rounds).
        fsync: the buffer service fsyncs its log before acknowledging an insert.
        sample_timeout_s: longest the learner waits for a batch before checking on actors.
        metrics: run Prometheus exporters (actors, learner, buffer) and write the file-SD file.
        bind_host: address the buffer service and the learner's exporter bind (loopback by
            default). For actors on other machines set the head node's IP: the service then
            requires its token, which the launcher always sets, and each actor's exporter binds
            its own node's IP.
        buffer_repair: start (and restart) the buffer service with `--repair`: from a damaged
            buffer folder it keeps what can still be read and discards, naming them in its
            log, the records that cannot; off, it refuses to start on damage and so does the
            run (`credit buffer verify DIR` reports what is there).
    """

    actors: int = 2
    actor_cpus: float = 1.0
    publish_interval: int = 1
    rate_slack: int = 2
    fsync: bool = True
    sample_timeout_s: float = 30.0
    metrics: bool = True
    bind_host: str = "127.0.0.1"
    buffer_repair: bool = False

    def validate(self) -> None:
        if self.actors < 1:
            raise ValueError(f"actors must be >= 1, got {self.actors}")
        if self.actor_cpus < 0:
            raise ValueError(f"actor_cpus must be >= 0, got {self.actor_cpus}")
        for name in ("publish_interval", "rate_slack"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.sample_timeout_s <= 0:
            raise ValueError(f"sample_timeout_s must be > 0, got {self.sample_timeout_s}")
        if not self.bind_host:
            raise ValueError("bind_host must name an address, e.g. 127.0.0.1")


# The measured layers alone; any other recipe r adds the layer recipes/<algo>.<r>.yaml.
@dataclass(frozen=True)
class TrainConfig:
    """A whole run. `algo` is an instance of the registry's config class for `algo_name`;
    `recipe` names the layer `recipes/<algo_name>.<recipe>.yaml` that was merged on top of the
    shipped layers ("shipped": none; `recipe_file`)."""

    algo_name: str
    algo: Any
    env: EnvConfig
    exploration: ExplorationConfig
    replay: ReplayConfig
    cycling: CyclingConfig
    run: RunConfig
    cluster: ClusterConfig
    recipe: str = SHIPPED_RECIPE

    def to_yaml_dict(self) -> dict[str, Any]:
        return {
            "algo_name": self.algo_name,
            "recipe": self.recipe,
            "algo": to_dict(self.algo),
            "env": to_dict(self.env),
            "exploration": to_dict(self.exploration),
            "replay": to_dict(self.replay),
            "cycling": to_dict(self.cycling),
            "run": to_dict(self.run),
            "cluster": to_dict(self.cluster),
        }


SECTIONS = {
    "env": EnvConfig,
    "exploration": ExplorationConfig,
    "replay": ReplayConfig,
    "cycling": CyclingConfig,
    "run": RunConfig,
    "cluster": ClusterConfig,
}


def load_train_config(
    algo: str | None, env_id: str | None, files: list[str] = (), overrides: list[str] = ()
) -> TrainConfig:
    """Merge defaults <- shipped YAML <- user files <- --set overrides, then validate.

    `algo`/`env_id` from the command line win over `algo_name`/`env.id` in files.
    """
    user: dict[str, Any] = {}
    for f in files:
        user = deep_merge(user, read_yaml(f))
    user = deep_merge(user, parse_overrides(list(overrides)))
    algo = algo or user.get("algo_name") or "rdn"
    env_id = env_id or user.get("env", {}).get("id") or EnvConfig.id
    # Fail on an unknown algo or env before looking for its YAML layers.
    try:
        get_algo(algo)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    try:
        get_spec(env_id)
    except EnvError as e:
        raise ConfigError(f"env: {e}") from None
    recipe = recipe_name(user.get("recipe", SHIPPED_RECIPE))
    layers = default_files(algo, env_id)
    extra = recipe_file(algo, recipe)
    data: dict[str, Any] = {}
    for path in layers if extra is None else [*layers, extra]:
        data = deep_merge(data, read_yaml(path))
    data = deep_merge(data, user)
    data["recipe"] = recipe
    data["algo_name"] = algo
    data.setdefault("env", {})["id"] = env_id
    return build_train_config(data)


def moved_keys(data: dict[str, Any]) -> dict[str, Any]:
    """`data` with keys that moved read into their new place, so that the config.yaml of an
    older run still resumes: cluster.max_policy_lag (cluster mode only, before the one loop)
    is run.max_policy_lag (both modes); RDN's retired keys are dropped where they hold what RDN
    still computes (`learner.rdn.drop_retired_keys`).

    Raises:
        ConfigError: both names given, with different values.
    """
    algo = data.get("algo")
    if data.get("algo_name") == "rdn" and isinstance(algo, dict):
        try:
            data = {**data, "algo": drop_retired_keys(algo)}
        except ValueError as e:
            raise ConfigError(str(e)) from None
    cluster = data.get("cluster")
    if not isinstance(cluster, dict) or "max_policy_lag" not in cluster:
        return data
    cluster = dict(cluster)
    lag = cluster.pop("max_policy_lag")
    run = dict(data.get("run") or {})
    if run.get("max_policy_lag", lag) != lag:
        raise ConfigError(
            f"cluster.max_policy_lag={lag} and run.max_policy_lag={run['max_policy_lag']}: "
            "the key is run.max_policy_lag now; give it once"
        )
    run["max_policy_lag"] = lag
    log.warning("cluster.max_policy_lag is run.max_policy_lag now (it applies in both modes)")
    return {**data, "cluster": cluster, "run": run}


def build_train_config(data: dict[str, Any]) -> TrainConfig:
    """A TrainConfig from complete data (`TrainConfig.to_yaml_dict()` form), validated."""
    data = moved_keys(data)
    try:
        spec = get_algo(data.get("algo_name", ""))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    unknown = [k for k in data if k not in (*SECTIONS, "algo", "algo_name", "recipe")]
    if unknown:
        valid = ", ".join(SECTIONS)
        raise ConfigError(
            f"unknown config section {unknown[0]!r}; valid sections: algo, {valid} (and the "
            "key recipe)"
        )
    built = {
        name: build(cls, data.get(name) or {}, prefix=f"{name}.") for name, cls in SECTIONS.items()
    }
    algo_cfg = build(spec.config_cls, data.get("algo") or {}, prefix="algo.")
    recipe = recipe_name(data.get("recipe", SHIPPED_RECIPE))
    recipe_file(spec.name, recipe)  # an unknown recipe is an error that lists the valid ones
    return TrainConfig(algo_name=spec.name, algo=algo_cfg, recipe=recipe, **built)
