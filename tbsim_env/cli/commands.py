"""The ``tbsim`` commands as typed configs: each class is one subcommand, its fields the
options, its docstring the help (``tbsim_env.core.config_cli`` builds the parser from them).

Shared option groups are base classes: ``DataOptions`` (which scenarios), ``RolloutOptions``
(which policy, how many rollouts) and ``ShardOptions`` (resumable shards, Ray).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tbsim_env.core import constants as C
from tbsim_env.core.config_cli import option


def _all_policies() -> tuple[str, ...]:
    from policies import policy_names

    return policy_names()


def _agent_policies() -> tuple[str, ...]:
    from policies import policy_names

    return policy_names(agents=True)


WOSAC_VERSIONS = ("wosac2024", "wosac2025")


@dataclass(frozen=True, kw_only=True)
class Demo:
    """Simulate the embedded generated scenes and write a video.

    Attributes:
        out: video path (.mp4 or .gif).
        scenarios: how many default scenes to render.
        npc_policy: policy of the NPCs.
        steps: steps to simulate (default: all).
        fps: video frames per second.
    """

    out: str = "tbsim_demo.mp4"
    scenarios: int = 1
    npc_policy: str = field(default="trafficbots", metadata=option(choices=_agent_policies))
    steps: int | None = None
    fps: int = 10


@dataclass(frozen=True, kw_only=True)
class Info:
    """One line per scenario of scenario files (TFRecord, JSON, pickle).

    Attributes:
        files: scenario files, globs or folders.
        skip_bad: warn and skip corrupt records.
    """

    files: tuple[str, ...] = field(metadata=option(positional=True))
    skip_bad: bool = False


@dataclass(frozen=True, kw_only=True)
class Render:
    """Simulate one scenario and write a video of all of it (the SDC follows its log to the
    end; a collision or leaving the road is drawn, not the end of the video).

    Attributes:
        file: a scenario file (TFRecord, JSON, pickle).
        scenario: scenario id (default: the first).
        out: video path (.mp4 or .gif).
        npc_policy: policy of every agent.
        fps: video frames per second.
    """

    file: str = field(metadata=option(positional=True))
    scenario: str | None = None
    out: str
    npc_policy: str = field(default="log_replay", metadata=option(choices=_agent_policies))
    fps: int = 10


@dataclass(frozen=True, kw_only=True)
class DataOptions:
    """Which scenarios a WOSAC command reads.

    Attributes:
        data: scenario files / globs / folders.
        skip_bad: warn and skip corrupt records.
    """

    data: tuple[str, ...]
    skip_bad: bool = False


@dataclass(frozen=True, kw_only=True)
class RolloutOptions:
    """How rollouts are made.

    Attributes:
        policy: policy of every agent.
        checkpoint: weights of the policy (TrafficBots).
        rollouts: rollouts per scenario (WOSAC: 32).
        seed: seed of the sampled rollouts.
        road_edge_weight: trafficbots: rank sampled rollouts by collided + this x departed
            agents (evaluated agents on the road at the current step that leave it; default:
            the shipped inference's 1; the spec's 0 ranks by collisions only).
    """

    policy: str = field(metadata=option(choices=_all_policies))
    checkpoint: str | None = None
    rollouts: int = 32
    seed: int = 0
    road_edge_weight: float | None = None


@dataclass(frozen=True, kw_only=True)
class ShardOptions:
    """Resumable shards, optionally as Ray tasks.

    Attributes:
        ray: run the shards as Ray tasks: a local Ray instance, or the cluster at ADDRESS.
        ray_workers: CPUs of a local Ray instance (default: all).
        work_dir: folder of finished shards, each written once; a rerun computes only the
            missing ones. Without --ray the shards run here, one by one. Default with --ray:
            --out DIR/ itself, OUT.shards, tbsim-evaluate-POLICY.shards or SUBMISSION.scores.
    """

    ray: str | None = field(
        default=None, metadata=option(nargs="?", const="local", metavar="ADDRESS")
    )
    ray_workers: int | None = None
    work_dir: str | None = None


@dataclass(frozen=True, kw_only=True)
class ExportWosac(DataOptions, RolloutOptions, ShardOptions):
    """Write a WOSAC SimAgentsChallengeSubmission.

    Attributes:
        out: OUT.binproto, or DIR/ for one file per input.
        shard_size: scenarios per shard (default: one shard per input file).
    """

    out: str
    shard_size: int | None = None


@dataclass(frozen=True, kw_only=True)
class WosacScore(DataOptions, ShardOptions):
    """Score a submission against the logged scenarios.

    Attributes:
        submission: a .binproto file or a folder of shards.
        version: the challenge's metric configuration.
        json: write every per-scenario field to this JSON.
    """

    submission: str
    version: str = field(default="wosac2025", metadata=option(choices=WOSAC_VERSIONS))
    json: str | None = None


@dataclass(frozen=True, kw_only=True)
class Evaluate(DataOptions, RolloutOptions, ShardOptions):
    """Roll out a policy and score it (no proto written).

    Attributes:
        version: the challenge's metric configuration.
        json: write every per-scenario field to this JSON.
        plot: PNG of log vs simulated feature histograms.
        shard_size: scenarios per shard (default: one shard per input file).
    """

    version: str = field(default="wosac2025", metadata=option(choices=WOSAC_VERSIONS))
    json: str | None = None
    plot: str | None = None
    shard_size: int | None = None


@dataclass(frozen=True, kw_only=True)
class View:
    """Write a self-contained HTML viewer of a scenario's rollouts.

    Attributes:
        scenario: a scenario file (TFRecord, pickle, JSON), glob or folder.
        scenario_id: which scenario (default: the first).
        submission: show the rollouts of this .binproto (not with --policy).
        policy: simulate this policy (not with --submission).
        rollouts: --policy: rollouts to simulate.
        seed: --policy: seed (as export-wosac).
        checkpoint: --policy: weights of the policy (TrafficBots).
        out: HTML file to write.
    """

    scenario: str = field(metadata=option(positional=True))
    scenario_id: str | None = None
    submission: str | None = None
    policy: str | None = field(default=None, metadata=option(choices=_all_policies))
    rollouts: int = 8
    seed: int = 0
    checkpoint: str | None = None
    out: str

    def __post_init__(self) -> None:
        if self.submission and self.policy:
            raise ValueError("tbsim view shows a --submission or a --policy, not both")


@dataclass(frozen=True, kw_only=True)
class Preprocess:
    """Build a sharded token cache for training.

    Attributes:
        sources: files / globs / folders, or generated:LAYOUTS:A-B, e.g.
            generated:intersection,merge:0-99 (generated-recorded:LAYOUTS:A-B for scenes with
            parked vehicles and tracker jitter as real logs have them).
        out: cache folder (shards + manifest.json).
        workers: preprocessing processes.
        shard_size: scenes per shard file.
        max_map_pieces: map pieces per scene (those farthest from the relevant agents go first).
        max_traffic_lights: traffic-light tokens per scene.
        max_agents: agents per scene.
        eval_split: validation/test agent filters.
        exclude: scenario ids to hold out.
    """

    sources: tuple[str, ...] = field(metadata=option(positional=True))
    out: str
    workers: int = 2
    shard_size: int = 64
    max_map_pieces: int = C.DEFAULT_MAX_MAP_PIECES
    max_traffic_lights: int = C.DEFAULT_MAX_TRAFFIC_LIGHTS
    max_agents: int = C.DEFAULT_MAX_AGENTS
    eval_split: bool = False
    exclude: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True)
class Average:
    """Average the weights of TrafficBots checkpoints of one run (one config).

    Attributes:
        checkpoints: checkpoint base paths (2 or more).
        out: base path of the averaged checkpoint.
    """

    checkpoints: tuple[str, ...] = field(metadata=option(positional=True))
    out: str


@dataclass(frozen=True, kw_only=True)
class Benchmark(DataOptions, ShardOptions):
    """Score a planner driving the SDC on real scenes against log-replayed, IDM and TrafficBots
    traffic: nuPlan's closed-loop score and a PDM score (docs/benchmark.md).

    Attributes:
        planner: a built-in planner (expert, constant_velocity, idm) or PACKAGE.MODULE:NAME (a
            planner, a factory of one, or a function of one PlannerInput).
        traffic: comma-separated NPC policies, one run of every scene each.
        controlled: which agents the planner drives.
        seed: seed of the NPC sampling (the same seed gives the same JSON).
        npc_checkpoint: weights of trafficbots traffic (default: shipped).
        json: write the summary and every per-episode field to this JSON.
        plot: PNG of the score distributions per traffic mode.
        html: folder for viewer pages of the worst episodes, infractions marked.
        worst: how many worst episodes get a page.
        shard_size: scenarios per shard (default: one shard per input file).
        batch_size: scenes stepped together where the episodes stay the same (the SDC,
            log-replayed traffic, a planner with act_batch: the built-ins); 1: one at a time.
    """

    planner: str
    traffic: str = "log_replay,idm,trafficbots"
    controlled: str = field(default="sdc", metadata=option(choices=("sdc", "tracks_to_predict")))
    seed: int = 0
    npc_checkpoint: str | None = None
    json: str | None = None
    plot: str | None = None
    html: str | None = None
    worst: int = 5
    shard_size: int | None = None
    batch_size: int = 16


COMMANDS: dict[str, type] = {
    "demo": Demo,
    "info": Info,
    "render": Render,
    "export-wosac": ExportWosac,
    "wosac-score": WosacScore,
    "evaluate": Evaluate,
    "view": View,
    "preprocess": Preprocess,
    "average": Average,
    "benchmark": Benchmark,
}
"""Subcommand name -> its config (``train`` parses its own ``TrainConfig``)."""
