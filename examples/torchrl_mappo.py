"""Multi-agent PPO on TorchRL TensorDicts: every agent of the generated scenes learns at once.

All agents valid at the start are controlled (``controlled="all"``, up to 32 per scene); the
few others are NPCs of ``--npc-policy``. The env is ``TorchRLTrafficEnv`` (``BatchedTrafficEnv``
as a TorchRL ``EnvBase``), stepped with TorchRL's ``step_and_maybe_reset``. One policy is
shared by all agents (IPPO, the decentralised-critic member of the MAPPO family): a Gaussian
actor and a critic, each a TorchRL ``MultiAgentMLP`` with shared parameters, over a compact
per-agent slice of the observation (own history, next route points, nearest agents).
Advantages come from TorchRL's ``generalized_advantage_estimate`` per agent (truncated
episodes bootstrap from the value of the true last observation in ``("next", ...)``); the
clipped PPO loss is written out below and averaged over the agents active at each step
(``("agents", "mask")``).

    python examples/torchrl_mappo.py --time-limit 300 --plot docs/torchrl_mappo_curve.png
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn


@dataclass
class Args:
    seed: int = field(default=1, metadata={"help": "seed of the env and torch"})
    num_scenes: int = field(default=8, metadata={"help": "embedded generated scenes (1..8)"})
    npc_policy: str = field(default="constant_velocity", metadata={"help": "NPC policy"})
    offroad_ends: int = field(
        default=1, metadata={"help": "1: leaving the road ends an agent (one -1, as a collision)"}
    )
    num_envs: int = field(default=8, metadata={"help": "scene slots stepped at once (B)"})
    num_steps: int = field(default=80, metadata={"help": "steps per slot per iteration"})
    iterations: int = field(default=200, metadata={"help": "PPO iterations at most"})
    time_limit: float = field(default=0.0, metadata={"help": "stop after this many s (0: none)"})
    learning_rate: float = field(default=3e-4, metadata={"help": "Adam learning rate"})
    gamma: float = field(default=0.99, metadata={"help": "discount"})
    gae_lambda: float = field(default=0.95, metadata={"help": "GAE lambda"})
    update_epochs: int = field(default=4, metadata={"help": "epochs per iteration"})
    num_minibatches: int = field(default=4, metadata={"help": "minibatches per epoch"})
    clip_coef: float = field(default=0.2, metadata={"help": "PPO clip coefficient"})
    vf_coef: float = field(default=0.5, metadata={"help": "value loss coefficient"})
    max_grad_norm: float = field(default=0.5, metadata={"help": "gradient clip norm"})
    route_points: int = field(default=8, metadata={"help": "route points in the observation"})
    num_neighbours: int = field(default=8, metadata={"help": "nearest agents observed"})
    torch_threads: int = field(default=1, metadata={"help": "torch threads (env and net)"})
    plot: str = field(default="", metadata={"help": "save the learning curve PNG here"})


def parse_args(argv: list[str] | None = None) -> Args:
    """``Args`` from the command line (one ``--flag`` per field)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for f in dataclasses.fields(Args):
        kind = {"int": int, "float": float, "str": str}[str(f.type)]
        flag = "--" + f.name.replace("_", "-")
        p.add_argument(flag, type=kind, default=f.default, help=f.metadata["help"])
    return Args(**vars(p.parse_args(argv)))


# ---------------------------------------------------------------------- model
HIST_SCALE = (0.1, 0.1, 1.0, 1.0, 0.1)  # x, y (10 m), cos, sin, speed (10 m/s)
ATTR_SCALE = (0.2, 0.5, 1.0, 1.0, 1.0, 1.0, 0.1)  # length, width, type one-hot, speed


def features(obs, k: int) -> torch.Tensor:
    """Per-agent features [..., Q, F] from the group's observation TensorDict [..., Q]:
    own history and attributes, route points (20 m units), the k nearest agents' pose,
    current state, attributes and mask."""
    hist, attr = torch.tensor(HIST_SCALE), torch.tensor(ATTR_SCALE)
    lead = obs["ego_history"].shape[:-2]
    parts = [
        obs["ego_history"] * hist,
        obs["ego_attributes"] * attr,
        obs["route"] * 0.05,
        obs["agents_pose"][..., :k, :] * torch.tensor([0.05, 0.05, 1.0]),
        obs["agents"][..., :k, -1, :] * hist,
        obs["agents_attributes"][..., :k, :] * attr,
        obs["agents_mask"][..., :k],
    ]
    return torch.cat([p.reshape(*lead, -1) for p in parts], dim=-1)


def type_limits(obs) -> torch.Tensor:
    """[..., Q, 2] each agent's action limits (m/s^2, rad/s) from its type one-hot, so that
    normalised actions in [-1, 1] span every type's full range."""
    from tbsim_env.sim.dynamics import action_limits

    one_hot = obs["ego_attributes"][..., 2:6]  # vehicle, pedestrian, cyclist, other
    acc, yaw = action_limits(one_hot.argmax(-1) + 1)  # ObjectType: VEHICLE = 1, ...
    return torch.stack([acc, yaw], dim=-1)


class Agents(nn.Module):
    """Shared Gaussian actor and critic over per-agent features [..., Q, F]."""

    def __init__(self, num_features: int, num_agents: int) -> None:
        super().__init__()
        from torchrl.modules import MultiAgentMLP

        def mlp(out: int) -> nn.Module:
            return MultiAgentMLP(
                num_features, out, num_agents, centralized=False, share_params=True,
                depth=2, num_cells=128, activation_class=nn.Tanh,
            )  # fmt: skip

        self.actor, self.critic = mlp(2), mlp(1)
        self.log_std = nn.Parameter(torch.full((2,), -0.5))

    def dist(self, feat: torch.Tensor) -> torch.distributions.Normal:
        """Action distribution in normalised units ([-1, 1] = the action bounds)."""
        mean = self.actor(feat)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def value(self, feat: torch.Tensor) -> torch.Tensor:
        """[..., Q] state values."""
        return self.critic(feat)[..., 0]


# ---------------------------------------------------------------------- rollout
class Tracker:
    """Per-agent running episode returns; records each agent's return, goal, collision and
    off-road flags when its episode ends."""

    def __init__(self, b: int, q: int) -> None:
        self.running = torch.zeros(b, q)
        self.returns: list[float] = []
        self.goals: list[float] = []
        self.collisions: list[float] = []
        self.offroads: list[float] = []

    def update(self, acted: torch.Tensor, nxt) -> None:
        """acted [B, Q] bool; nxt: the step's ("next") TensorDict."""
        self.running += nxt["agents", "reward"][..., 0] * acted
        ended = acted & ~nxt["agents", "mask"]
        info = nxt["agents", "info"]
        self.returns += self.running[ended].tolist()
        self.goals += info["goal_reached"][ended].tolist()
        self.collisions += info["collision"][ended].tolist()
        self.offroads += info["offroad"][ended].tolist()
        self.running[ended] = 0.0


def collect(env, agents: Agents, td, args: Args, tracker: Tracker):
    """``args.num_steps`` steps of every slot with the current policy.

    Returns:
        (batch TensorDict [B, T] with ``feat`` / ``next_feat`` [B, T, Q, F], ``act``,
        ``logp``, ``value`` and the step's mask, reward and done flags; the root TensorDict to
        continue from).
    """
    from tensordict import TensorDict

    steps = []
    for _ in range(args.num_steps):
        feat = features(td["agents", "observation"], args.num_neighbours)
        with torch.no_grad():
            dist = agents.dist(feat)
            act = dist.sample()
            logp, value = dist.log_prob(act).sum(-1), agents.value(feat)
        td["agents", "action"] = act.clamp(-1.0, 1.0) * type_limits(td["agents", "observation"])
        data, td = env.step_and_maybe_reset(td)
        nxt = data["next"]
        acted = data["agents", "mask"]
        tracker.update(acted, nxt)
        steps.append(
            TensorDict(
                {
                    "feat": feat,
                    "act": act,
                    "logp": logp,
                    "value": value,
                    "mask": acted,
                    "next_feat": features(nxt["agents", "observation"], args.num_neighbours),
                    "reward": nxt["agents", "reward"][..., 0],
                    "done": nxt["agents", "done"][..., 0],
                    "terminated": nxt["agents", "terminated"][..., 0],
                },
                batch_size=acted.shape,
            )
        )
    return torch.stack(steps, dim=1), td  # [B, T, Q]


def advantages(agents: Agents, batch, args: Args) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE per agent (TorchRL's functional estimator, time on dim -2): (advantage, value
    target), each [B, T, Q]."""
    from torchrl.objectives.value.functional import generalized_advantage_estimate

    with torch.no_grad():
        next_value = agents.value(batch["next_feat"])

    def per_agent(x: torch.Tensor) -> torch.Tensor:
        return x.transpose(1, 2)[..., None]  # [B, T, Q] -> [B, Q, T, 1]

    adv, target = generalized_advantage_estimate(
        args.gamma, args.gae_lambda,
        per_agent(batch["value"]), per_agent(next_value), per_agent(batch["reward"]),
        per_agent(batch["done"]), per_agent(batch["terminated"]),
    )  # fmt: skip
    return adv[..., 0].transpose(1, 2), target[..., 0].transpose(1, 2)


# ---------------------------------------------------------------------- update
def ppo_update(agents: Agents, opt: torch.optim.Optimizer, batch, args: Args) -> dict:
    """Clipped PPO over minibatches of (slot, step) rows [Q agents each]; every loss term is
    averaged over the agents active at that step. Returns loss stats."""
    adv, target = advantages(agents, batch, args)
    rows = {k: batch[k].flatten(0, 1) for k in ("feat", "act", "logp", "value", "mask")}
    rows["adv"], rows["target"] = adv.flatten(0, 1), target.flatten(0, 1)  # [B * T, Q]
    n = len(rows["adv"])
    size = max(1, n // args.num_minibatches)
    clipfracs, kl, v_loss = [], torch.zeros(()), torch.zeros(())
    for _ in range(args.update_epochs):
        order = torch.randperm(n)
        for start in range(0, n, size):
            mb = {k: v[order[start : start + size]] for k, v in rows.items()}
            m = mb["mask"].float()
            count = m.sum().clamp_min(1.0)

            def masked_mean(x: torch.Tensor, m=m, count=count) -> torch.Tensor:
                return (x * m).sum() / count

            dist = agents.dist(mb["feat"])
            logratio = (dist.log_prob(mb["act"]).sum(-1) - mb["logp"]) * m
            ratio = logratio.exp()
            mean = masked_mean(mb["adv"])
            std = masked_mean((mb["adv"] - mean) ** 2).sqrt()
            a = (mb["adv"] - mean) / (std + 1e-8)
            clipped = ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)
            pg_loss = masked_mean(torch.max(-a * ratio, -a * clipped))
            v_loss = 0.5 * masked_mean((agents.value(mb["feat"]) - mb["target"]) ** 2)
            loss = pg_loss + args.vf_coef * v_loss
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agents.parameters(), args.max_grad_norm)
            opt.step()
            with torch.no_grad():
                kl = masked_mean((ratio - 1) - logratio)
                clipfracs.append(float(masked_mean(((ratio - 1).abs() > args.clip_coef).float())))
    return {
        "approx_kl": float(kl),
        "clipfrac": float(np.mean(clipfracs)),
        "v_loss": float(v_loss.detach()),
    }


# ---------------------------------------------------------------------- reporting
def save_plot(rows: list[dict], path: str, title: str) -> None:
    """Per-agent episode return, goal-reach, collision and off-road rate against agent steps
    (the rates: share of the agent episodes that ended in the iteration)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([r["agent_steps"] for r in rows], float)
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    keys = ("episode_return", "goal_rate", "collision_rate", "offroad_rate")
    for ax, key in zip(axes, keys):
        y = np.array([r[key] for r in rows], float)
        ax.plot(steps, y, color="0.7", lw=0.8)
        w = max(1, len(y) // 15)
        ax.plot(steps[w - 1 :], np.convolve(y, np.ones(w) / w, mode="valid"), color="C0", lw=2)
        ax.set_xlabel("agent steps")
        ax.set_title(key.replace("_", " ") + " (per agent episode)")
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def summary_row(it: int, agent_steps: int, elapsed: float, tracker: Tracker, stats: dict):
    """One iteration's numbers (means over the agent episodes that ended in it)."""
    row = {
        "iteration": it,
        "agent_steps": agent_steps,
        "time_s": round(elapsed, 1),
        "episodes": len(tracker.returns),
        "episode_return": _mean(tracker.returns),
        "goal_rate": _mean(tracker.goals),
        "collision_rate": _mean(tracker.collisions),
        "offroad_rate": _mean(tracker.offroads),
        **stats,
    }
    tracker.returns, tracker.goals, tracker.collisions, tracker.offroads = [], [], [], []
    return row


def make_env(args: Args):
    """``TorchRLTrafficEnv`` over the embedded generated scenes, every agent controlled."""
    from tbsim_env.core.config import EnvConfig, TerminationConfig
    from tbsim_env.data.generator import default_scenarios
    from tbsim_env.integrations.torchrl import TorchRLTrafficEnv

    config = EnvConfig(termination=TerminationConfig(offroad=bool(args.offroad_ends)))
    return TorchRLTrafficEnv(
        scenarios=default_scenarios(args.num_scenes),
        batch_size=args.num_envs,
        controlled="all",
        npc_policy=args.npc_policy,
        seed=args.seed,
        config=config,
        route_points=args.route_points,
        torch_threads=args.torch_threads,
    )


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(argv)
    from tqdm import tqdm

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)
    env = make_env(args)
    td = env.reset()
    feat = features(td["agents", "observation"], args.num_neighbours)
    agents = Agents(feat.shape[-1], env.num_agents)
    opt = torch.optim.Adam(agents.parameters(), lr=args.learning_rate, eps=1e-5)
    tracker = Tracker(args.num_envs, env.num_agents)
    rows, agent_steps, start = [], 0, time.time()
    bar = tqdm(range(1, args.iterations + 1), desc="PPO", unit="it")
    for it in bar:
        batch, td = collect(env, agents, td, args, tracker)
        agent_steps += int(batch["mask"].sum())
        stats = ppo_update(agents, opt, batch, args)
        rows.append(summary_row(it, agent_steps, time.time() - start, tracker, stats))
        r = rows[-1]
        bar.set_postfix(
            ret=f"{r['episode_return']:.2f}", goal=f"{r['goal_rate']:.2f}",
            coll=f"{r['collision_rate']:.2f}", sps=int(agent_steps / r["time_s"]),
        )  # fmt: skip
        if args.time_limit and r["time_s"] > args.time_limit:
            break
    print_table(rows)
    if args.plot:
        title = (
            f"TorchRL multi-agent PPO, all agents of {args.num_scenes} generated scenes, "
            f"B={args.num_envs}, {rows[-1]['time_s']:.0f} s on {args.torch_threads} CPU thread(s)"
        )
        save_plot(rows, args.plot, title)
        print(f"learning curve written to {args.plot}")
    return rows


def print_table(rows: list[dict]) -> None:
    """Iteration table (every ~10th row and the last) and the first vs last tenth."""
    print(" iter  agent_steps  time_s  episodes  return   goal  collision  offroad")
    stride = max(1, len(rows) // 10)
    for r in rows[::stride] + ([rows[-1]] if (len(rows) - 1) % stride else []):
        print(
            f"{r['iteration']:5d} {r['agent_steps']:12d} {r['time_s']:7.0f} {r['episodes']:9d} "
            f"{r['episode_return']:7.3f} {r['goal_rate']:6.3f} {r['collision_rate']:10.3f} "
            f"{r['offroad_rate']:8.3f}"
        )
    k = max(1, len(rows) // 10)
    for name, part in (("first", rows[:k]), ("last", rows[-k:])):
        keys = ("episode_return", "goal_rate", "collision_rate", "offroad_rate")
        mean = {key: np.nanmean([r[key] for r in part]) for key in keys}
        print(
            f"{name} {k} iterations: return {mean['episode_return']:.3f}, "
            f"goal {mean['goal_rate']:.3f}, collision {mean['collision_rate']:.3f}, "
            f"off-road {mean['offroad_rate']:.3f}"
        )


if __name__ == "__main__":
    main()
