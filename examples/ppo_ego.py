"""PPO for the self-driving car (SDC) among NPCs, single file, CleanRL style.

The SDC of each scene is the learner; every other agent is an NPC of ``--npc-policy``
(``constant_velocity``, ``log_replay``, or ``trafficbots`` once that policy is registered).
Rollouts come from ``BatchedTrafficEnv`` (``--num-envs`` scenes stepped at once, torch tensors,
same-step autoreset); the reward is the environment's ``RewardConfig``: progress along the
logged route, goal reached, collision and off-road penalties.

The policy sees a compact slice of the pairwise-relative observation: its own history and
attributes, the next points of its logged route, and the nearest agents (relative pose,
attributes, mask). Truncated episodes are bootstrapped from the value of their final
observation.

    python examples/ppo_ego.py --total-timesteps 600000 --plot docs/ppo_ego_curve.png
"""

from __future__ import annotations

import csv
import json
import os
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
from safetensors.torch import load_file, save_file
from torch.distributions.normal import Normal

from policies import policy_names
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.config_cli import config_parser, option, parse_config
from tbsim_env.env.vector_env import ROUTE_KEY, BatchedTrafficEnv

ROUTE_SPACING = 5.0
"""m between the route points the agent sees."""


@dataclass(frozen=True)
class Args:
    """PPO of the SDC on the batched env (CleanRL style).

    Attributes:
        seed: seed of the env, torch and numpy.
        num_scenes: embedded generated scenes (1..8).
        npc_policy: policy of the NPCs.
        npc_checkpoint: TrafficBots checkpoint.
        total_timesteps: agent steps to train.
        time_limit: stop after this many s (0: none).
        learning_rate: Adam learning rate.
        num_envs: scenes stepped in parallel.
        num_steps: steps per env per rollout.
        anneal_lr: linearly anneal the learning rate.
        gamma: discount.
        gae_lambda: GAE lambda.
        num_minibatches: minibatches per epoch.
        update_epochs: epochs per rollout.
        clip_coef: PPO clip coefficient.
        ent_coef: entropy coefficient.
        vf_coef: value loss coefficient.
        max_grad_norm: gradient clip norm.
        route_points: route points in the observation.
        num_neighbours: nearest agents observed.
        torch_threads: torch threads (env and net).
        csv: write per-iteration stats to this CSV.
        plot: save the learning curve PNG here.
        tensorboard: TensorBoard log dir (optional).
        save_model: save the agent here (``PATH.safetensors`` weights + ``PATH.json`` settings;
            ``PPOPlanner`` drives with it, e.g. in ``tbsim benchmark``).
    """

    seed: int = 1
    num_scenes: int = 8
    npc_policy: str = field(
        default="constant_velocity", metadata=option(choices=lambda: policy_names(agents=True))
    )
    npc_checkpoint: str = ""
    total_timesteps: int = 600_000
    time_limit: float = 0.0
    learning_rate: float = 3e-4
    num_envs: int = 32
    num_steps: int = 128
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    num_minibatches: int = 8
    update_epochs: int = 4
    clip_coef: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    route_points: int = 8
    num_neighbours: int = 8
    torch_threads: int = 1
    csv: str = ""
    plot: str = ""
    tensorboard: str = ""
    save_model: str = ""


def parse_args() -> Args:
    """``Args`` from the command line (one ``--flag`` per field, help from the docstring)."""
    return parse_config(Args, config_parser(Args).parse_args())


def features(obs: dict[str, torch.Tensor], k: int) -> torch.Tensor:
    """Flat features [B, F] of the SDC (agent slot 0) from the observation dict [B, Q, ...].

    Distances are scaled to tens of metres, speeds to 10 m/s.
    """
    scale = torch.tensor([0.1, 0.1, 1.0, 1.0, 0.1])
    parts = [
        (obs["ego_history"][:, 0] * scale).flatten(1),
        obs["ego_attributes"][:, 0] * torch.tensor([0.2, 0.5, 1, 1, 1, 1, 0.1]),
        (obs[ROUTE_KEY][:, 0] * 0.05).flatten(1),
        (obs["agents_pose"][:, 0, :k] * torch.tensor([0.05, 0.05, 1.0])).flatten(1),
        (obs["agents"][:, 0, :k, -1] * scale).flatten(1),  # their current state, own frame
        (obs["agents_attributes"][:, 0, :k] * torch.tensor([0.2, 0.5, 1, 1, 1, 1, 0.1])).flatten(1),
        obs["agents_mask"][:, 0, :k],
    ]
    return torch.cat(parts, dim=-1)


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """Gaussian actor and critic MLPs over the flat SDC features."""

    def __init__(self, num_features: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(
            layer_init(nn.Linear(num_features, 128)),
            nn.Tanh(),
            layer_init(nn.Linear(128, 128)),
            nn.Tanh(),
            layer_init(nn.Linear(128, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(num_features, 128)),
            nn.Tanh(),
            layer_init(nn.Linear(128, 128)),
            nn.Tanh(),
            layer_init(nn.Linear(128, 2), std=0.01),
        )
        self.actor_logstd = nn.Parameter(torch.full((1, 2), -0.5))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(
        self, x: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(action [B, 2] in normalised units, log-prob [B], entropy [B], value [B, 1])."""
        mean = self.actor_mean(x)
        std = self.actor_logstd.expand_as(mean).exp()
        probs = Normal(mean, std)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.critic(x)


def save_agent(agent: Agent, args: Args, action_high: np.ndarray, path: str) -> None:
    """The agent as ``path.safetensors`` (weights, no pickle) and ``path.json`` (what
    ``PPOPlanner`` needs to rebuild its features and actions)."""
    base = str(path).removesuffix(".safetensors")
    save_file({k: v.contiguous() for k, v in agent.state_dict().items()}, base + ".safetensors")
    meta = {
        "num_features": agent.actor_mean[0].in_features,
        "num_neighbours": args.num_neighbours,
        "route_points": args.route_points,
        "route_spacing": ROUTE_SPACING,
        "action_high": [float(x) for x in action_high],
    }
    Path(base + ".json").write_text(json.dumps(meta, indent=1))


class PPOPlanner:
    """A saved PPO agent as a planner of ``tbsim_env.benchmark`` (the actor's mean action).

    Its features are rebuilt from the planner's input as the training env gave them: the
    observation with a batch and an agent axis, the logged route resampled at the training
    spacing. ``tbsim benchmark --planner ppo_ego:make_planner`` (run from ``examples/``, or
    with it on ``PYTHONPATH``) loads the agent named by ``$PPO_EGO_AGENT``.
    """

    name = "ppo_ego"

    def __init__(self, path: str) -> None:
        base = str(path).removesuffix(".safetensors")
        self.meta = json.loads(Path(base + ".json").read_text())
        self.agent = Agent(self.meta["num_features"])
        self.agent.load_state_dict(load_file(base + ".safetensors"))
        self.agent.eval()
        self.high = torch.tensor(self.meta["action_high"])

    def act(self, x) -> np.ndarray:
        obs = {k: torch.as_tensor(np.asarray(v, np.float32))[None, None] for k, v in
               x.observation.items()}  # fmt: skip
        obs[ROUTE_KEY] = torch.as_tensor(self._route(x.route))[None, None]
        with torch.no_grad():
            mean = self.agent.actor_mean(features(obs, self.meta["num_neighbours"]))
        return (mean.clamp(-1.0, 1.0) * self.high)[0].numpy()

    def _route(self, route: np.ndarray) -> np.ndarray:
        """[R, 2] points of ``route`` [P, 2] at the training arc lengths (linear between
        the given points, held at the last one)."""
        pts = np.vstack([np.zeros((1, 2)), np.asarray(route, np.float64)])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        want = np.arange(1, self.meta["route_points"] + 1) * self.meta["route_spacing"]
        want = np.minimum(want, arc[-1])
        return np.stack([np.interp(want, arc, pts[:, i]) for i in (0, 1)], -1).astype(np.float32)


def make_planner() -> PPOPlanner:
    """``PPOPlanner`` of the agent saved at ``$PPO_EGO_AGENT`` (default ``ppo_ego``)."""
    return PPOPlanner(os.environ.get("PPO_EGO_AGENT", "ppo_ego"))


def save_plot(rows: list[dict], path: str, title: str) -> None:
    """Learning curve: episode return, goal-reach and collision rate against agent steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([r["global_step"] for r in rows], float)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, key, label in zip(
        axes,
        ("episode_return", "goal_rate", "collision_rate"),
        ("episode return", "goal-reach rate", "collision rate"),
    ):
        y = np.array([r[key] for r in rows], float)
        ax.plot(steps, y, color="0.7", lw=0.8)
        w = max(1, len(y) // 15)
        smooth = np.convolve(y, np.ones(w) / w, mode="valid")
        ax.plot(steps[w - 1 :], smooth, color="C0", lw=2)
        ax.set_xlabel("agent steps")
        ax.set_title(label)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    args = parse_args()
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    num_iterations = max(1, args.total_timesteps // batch_size)

    # TRY NOT TO MODIFY: seeding
    random.seed(args.seed)
    rng = np.random.default_rng(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)

    from tbsim_env.data.generator import default_scenarios

    envs = BatchedTrafficEnv(
        default_scenarios(args.num_scenes),
        args.num_envs,
        controlled="sdc",
        npc_policy=args.npc_policy,
        npc_kwargs={"checkpoint": args.npc_checkpoint} if args.npc_checkpoint else None,
        config=EnvConfig(),
        seed=args.seed,
        route_points=args.route_points,
        route_spacing=ROUTE_SPACING,
        torch_threads=args.torch_threads,
    )
    high = torch.from_numpy(envs.action_high)
    writer = None
    if args.tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(args.tensorboard)

    obs_dict, _ = envs.reset(seed=args.seed)
    next_obs = features(obs_dict, args.num_neighbours)
    agent = Agent(next_obs.shape[1])
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    # ALGO Logic: Storage setup
    obs = torch.zeros((args.num_steps, args.num_envs, next_obs.shape[1]))
    actions = torch.zeros((args.num_steps, args.num_envs, 2))
    logprobs = torch.zeros((args.num_steps, args.num_envs))
    rewards = torch.zeros((args.num_steps, args.num_envs))
    dones = torch.zeros((args.num_steps, args.num_envs))
    values = torch.zeros((args.num_steps, args.num_envs))

    global_step, start_time = 0, time.time()
    next_done = torch.zeros(args.num_envs)
    collided = torch.zeros(args.num_envs, dtype=torch.bool)
    rows: list[dict] = []
    csv_file = open(args.csv, "w", newline="") if args.csv else None  # noqa: SIM115
    csv_writer = None
    for iteration in range(1, num_iterations + 1):
        if args.anneal_lr:
            frac = 1.0 - (iteration - 1.0) / num_iterations
            optimizer.param_groups[0]["lr"] = frac * args.learning_rate
        ep_returns, ep_goals, ep_colls, ep_lens = [], [], [], []
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs[step] = next_obs
            dones[step] = next_done

            # ALGO LOGIC: action logic
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
                values[step] = value.flatten()
            actions[step] = action
            logprobs[step] = logprob

            # TRY NOT TO MODIFY: execute the game and log data.
            env_action = (action.clamp(-1.0, 1.0) * high)[:, None, :]
            obs_dict, reward, term, trunc, info = envs.step(env_action)
            r = reward[:, 0].clone()
            truncated = trunc[:, 0]
            if bool(truncated.any()):
                # Bootstrap time-limit truncations from the final observation's value.
                final = features(info["final_obs"], args.num_neighbours)[truncated]
                with torch.no_grad():
                    r[truncated] += args.gamma * agent.get_value(final).flatten()
            rewards[step] = r
            next_obs = features(obs_dict, args.num_neighbours)
            done = info["done"]
            next_done = done.float()
            collided |= info["collision"][:, 0] & info["active"][:, 0]
            for i in done.nonzero(as_tuple=True)[0].tolist():
                ep_returns.append(float(info["episode_return"][i, 0]))
                ep_goals.append(float(info["goal_reached"][i, 0]))
                ep_colls.append(float(collided[i]))
                ep_lens.append(int(info["episode_length"][i]))
            collided &= ~done

        # bootstrap value if not done
        with torch.no_grad():
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = 0
            for t in reversed(range(args.num_steps)):
                if t == args.num_steps - 1:
                    nextnonterminal = 1.0 - next_done
                    nextvalues = next_value
                else:
                    nextnonterminal = 1.0 - dones[t + 1]
                    nextvalues = values[t + 1]
                delta = rewards[t] + args.gamma * nextvalues * nextnonterminal - values[t]
                lastgaelam = delta + args.gamma * args.gae_lambda * nextnonterminal * lastgaelam
                advantages[t] = lastgaelam
            returns = advantages + values

        # flatten the batch
        b_obs = obs.reshape(-1, obs.shape[-1])
        b_logprobs = logprobs.reshape(-1)
        b_actions = actions.reshape(-1, 2)
        b_advantages = advantages.reshape(-1)
        b_returns = returns.reshape(-1)
        b_values = values.reshape(-1)

        # Optimizing the policy and value network
        b_inds = np.arange(batch_size)
        clipfracs = []
        for _epoch in range(args.update_epochs):
            rng.shuffle(b_inds)
            for start in range(0, batch_size, minibatch_size):
                mb_inds = b_inds[start : start + minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(
                    b_obs[mb_inds], b_actions[mb_inds]
                )
                logratio = newlogprob - b_logprobs[mb_inds]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()
                    clipfracs += [((ratio - 1.0).abs() > args.clip_coef).float().mean().item()]
                mb_adv = b_advantages[mb_inds]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
                pg_loss1 = -mb_adv * ratio
                pg_loss2 = -mb_adv * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
                pg_loss = torch.max(pg_loss1, pg_loss2).mean()
                newvalue = newvalue.view(-1)
                v_loss_unclipped = (newvalue - b_returns[mb_inds]) ** 2
                v_clipped = b_values[mb_inds] + torch.clamp(
                    newvalue - b_values[mb_inds], -args.clip_coef, args.clip_coef
                )
                v_loss_clipped = (v_clipped - b_returns[mb_inds]) ** 2
                v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()

        elapsed = time.time() - start_time
        if ep_returns:
            row = {
                "iteration": iteration,
                "global_step": global_step,
                "time_s": round(elapsed, 1),
                "episodes": len(ep_returns),
                "episode_return": float(np.mean(ep_returns)),
                "goal_rate": float(np.mean(ep_goals)),
                "collision_rate": float(np.mean(ep_colls)),
                "episode_length": float(np.mean(ep_lens)),
                "approx_kl": float(approx_kl),
                "clipfrac": float(np.mean(clipfracs)),
            }
            rows.append(row)
            print(
                f"iter {iteration:4d} step {global_step:8d} t {elapsed:6.0f}s  "
                f"return {row['episode_return']:6.3f}  goal {row['goal_rate']:.2f}  "
                f"collision {row['collision_rate']:.2f}  len {row['episode_length']:5.1f}  "
                f"SPS {int(global_step / elapsed)}",
                flush=True,
            )
            if csv_file is not None:
                if csv_writer is None:
                    csv_writer = csv.DictWriter(csv_file, fieldnames=list(row))
                    csv_writer.writeheader()
                csv_writer.writerow(row)
                csv_file.flush()
            if writer is not None:
                for key in ("episode_return", "goal_rate", "collision_rate", "episode_length"):
                    writer.add_scalar(f"charts/{key}", row[key], global_step)
                writer.add_scalar("losses/approx_kl", row["approx_kl"], global_step)
                writer.add_scalar("charts/SPS", int(global_step / elapsed), global_step)
        if args.time_limit and elapsed > args.time_limit:
            print(f"time limit {args.time_limit:.0f}s reached after {global_step} steps")
            break

    if csv_file is not None:
        csv_file.close()
    if writer is not None:
        writer.close()
    if args.save_model:
        save_agent(agent, args, envs.action_high, args.save_model)
    if args.plot and rows:
        title = (
            f"PPO ego (SDC) on {args.num_scenes} generated scenes, NPCs: {args.npc_policy}, "
            f"{args.num_envs} envs, {rows[-1]['time_s']:.0f} s on CPU"
        )
        save_plot(rows, args.plot, title)
        print(f"learning curve written to {args.plot}")


if __name__ == "__main__":
    main()
