"""PPO in one file, in CleanRL's style, on kgnavbench's batched vector env, then Table I's fixed
episodes of FloorPlan1's seen targets through `kgnavbench.evaluate_policy`.

    python examples/cleanrl_ppo.py                  # the defaults: 1.4M steps, 270 s on 2 cores
                                                    # (measured: seen-target SR 85.7%, seed 0)
    python examples/cleanrl_ppo.py --steps 4096 --envs 4 --episodes 1  # seconds: what `make test` runs

The env: `gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=64, ...)`, the batched NavigationVectorEnv
(every sub-env in FloorPlan1, a training target per episode) with the training protocol's keywords:
- max_steps=200: training episodes of at most 200 actions (evaluation keeps Table I's caps);
- curriculum_steps: starts near the destination first, ever farther over the first 60% of the steps
  (counted over all sub-envs). Without it plain RL meets no success: Stop ends the episode, so a
  policy never rewarded learns to Stop at once;
- observation="box": one float32 vector per sub-env (the view's encoder features and visible object
  types, then the target image's);
- autoreset_mode="same_step": every step is a real transition (the next episode's first observation
  comes back in the step that ended the last), so the rollout needs no mask for NEXT_STEP's reset steps.

The agent: an MLP actor and critic (2 x 256, tanh), PPO with GAE, clipped objective, entropy bonus
(CleanRL's ppo.py, its defaults except the sizes). Prints progress, then `evaluate_policy`'s summary as
JSON on its last line.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from torch.distributions.categorical import Categorical

import kgnavbench


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--steps", type=int, default=1_400_000, help="environment steps (all sub-envs)")
    p.add_argument("--envs", type=int, default=64, help="sub-envs of the vector env")
    p.add_argument("--rollout", type=int, default=128, help="steps per sub-env per update")
    p.add_argument("--lr", type=float, default=2.5e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--minibatches", type=int, default=4)
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--clip", type=float, default=0.2)
    p.add_argument("--ent-coef", type=float, default=0.01)
    p.add_argument("--vf-coef", type=float, default=0.5)
    p.add_argument("--max-grad-norm", type=float, default=0.5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=100, help="fixed episodes per target (of 100)")
    return p.parse_args()


def layer(n_in: int, n_out: int, std: float = np.sqrt(2)) -> nn.Linear:
    linear = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(linear.weight, std)
    nn.init.constant_(linear.bias, 0.0)
    return linear


class Agent(nn.Module):
    def __init__(self, n_obs: int, n_actions: int, hidden: int = 256):
        super().__init__()
        self.critic = nn.Sequential(
            layer(n_obs, hidden), nn.Tanh(), layer(hidden, hidden), nn.Tanh(), layer(hidden, 1, 1.0)
        )
        self.actor = nn.Sequential(
            layer(n_obs, hidden), nn.Tanh(), layer(hidden, hidden), nn.Tanh(), layer(hidden, n_actions, 0.01)
        )

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        probs = Categorical(logits=self.actor(x))
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(x)


def main() -> None:
    args = parse_args()
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    envs = gym.make_vec(
        "kgnavbench/FloorPlan1-v0",
        num_envs=args.envs,
        max_steps=200,
        curriculum_steps=int(0.6 * args.steps),
        observation="box",
        autoreset_mode="same_step",
    )
    n_obs, n_actions = envs.single_observation_space.shape[0], envs.single_action_space.n
    agent = Agent(n_obs, n_actions)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)

    batch = args.envs * args.rollout
    minibatch = batch // args.minibatches
    updates = max(1, args.steps // batch)
    obs = torch.zeros((args.rollout, args.envs, n_obs))
    actions = torch.zeros((args.rollout, args.envs), dtype=torch.long)
    logprobs = torch.zeros((args.rollout, args.envs))
    rewards = torch.zeros((args.rollout, args.envs))
    dones = torch.zeros((args.rollout, args.envs))
    values = torch.zeros((args.rollout, args.envs))

    start = time.perf_counter()
    next_obs = torch.as_tensor(envs.reset(seed=args.seed)[0])
    next_done = torch.zeros(args.envs)
    successes, episodes = 0, 0
    for update in range(1, updates + 1):
        optimizer.param_groups[0]["lr"] = args.lr * (1.0 - (update - 1.0) / updates)  # annealed
        for step in range(args.rollout):
            obs[step], dones[step] = next_obs, next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
            values[step], actions[step], logprobs[step] = value.flatten(), action, logprob
            next_obs, reward, terminated, truncated, infos = envs.step(action.numpy())
            rewards[step] = torch.as_tensor(reward, dtype=torch.float32)
            done = np.logical_or(terminated, truncated)
            next_obs, next_done = torch.as_tensor(next_obs), torch.as_tensor(done, dtype=torch.float32)
            ended = infos["_final_info"]
            successes += int(infos["final_info"]["success"][ended].sum())
            episodes += int(ended.sum())

        with torch.no_grad():  # GAE: the advantages and the returns
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages = torch.zeros_like(rewards)
            last = 0.0
            for t in reversed(range(args.rollout)):
                if t == args.rollout - 1:
                    nonterminal, following = 1.0 - next_done, next_value
                else:
                    nonterminal, following = 1.0 - dones[t + 1], values[t + 1]
                delta = rewards[t] + args.gamma * following * nonterminal - values[t]
                advantages[t] = last = delta + args.gamma * args.gae_lambda * nonterminal * last
            returns = advantages + values

        b_obs, b_actions = obs.reshape(-1, n_obs), actions.reshape(-1)
        b_logprobs, b_advantages = logprobs.reshape(-1), advantages.reshape(-1)
        b_returns = returns.reshape(-1)
        order = np.arange(batch)
        for _ in range(args.epochs):
            np.random.shuffle(order)
            for lo in range(0, batch, minibatch):
                mb = order[lo : lo + minibatch]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_actions[mb])
                ratio = (newlogprob - b_logprobs[mb]).exp()
                adv = b_advantages[mb]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip, 1 + args.clip)).mean()
                v_loss = 0.5 * ((newvalue.view(-1) - b_returns[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + args.vf_coef * v_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
        if update % 20 == 0 or update == updates:
            sr = 100 * successes / max(episodes, 1)
            print(
                f"{update * batch:>10,} steps  {time.perf_counter() - start:5.0f} s  "
                f"training episodes {episodes:,}, SR {sr:.1f}%  (curriculum reach {envs.unwrapped.reach()})",
                flush=True,
            )
            successes = episodes = 0

    def policy(observations: np.ndarray) -> np.ndarray:  # evaluate_policy's callable: one action per row
        with torch.no_grad():
            return agent.get_action_and_value(torch.as_tensor(observations))[0].numpy()

    result = kgnavbench.evaluate_policy(
        policy,
        split="train",
        kitchens=["FloorPlan1"],
        targets="seen",
        episodes=args.episodes,
        observation="box",
        seed=args.seed,
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
