"""Stage 10 — train: the learned methods' trainer. A synchronous batched A2C with the paper's A3C losses,
imitation learning (IL), target skill extension (TSE), checkpoints, logs and resumption.

Read it top to bottom:

1. Options and runs. `TrainOptions` holds every option a learned method shares (a plugin's `Config`
   extends it); `train_method` resolves a plugin's config into a run directory
   `runs/train/<method>-<hash>/` (a hash of the config, the plugin's source, the training code, frames,
   seed and kitchens), writes `config.json` once with the git revision, and calls the plugin's `train`
   hook.
2. The state space. The training kitchens' state graphs are concatenated into one global state space
   (per kitchen an offset into one next-state table, one success table, the object vectors and the
   per-state features of `models.state_features`), so `Navigators.step` — one step of every agent in
   every kitchen — is a handful of NumPy gathers with exactly the env's semantics (kgnavbench/env.py:
   -0.01 per step, +0.01 on the first arrival at a goal state, +10 on success, Stop ends the episode,
   starts at pitch 0 without the target in view and at least 10 actions from its destination).
3. The losses. `n_step_returns`, `actor_critic_loss` (policy gradient, value loss with weight
   `value_weight`, entropy bonus; optional per-sample weights for TSE's importance weights) and
   `imitation_loss` (cross-entropy on expert actions).
4. IL data (one expert trajectory per training target: the paper's walk back from the destination)
   and TSE (`SubtargetSampler`, `relabel`): per episode, 5 sub-targets sampled at random among the
   states that showed a novel object (a pickupable that is no target) or another agent's training
   target; each becomes "reach this state and Stop", with its view as the target image, rewards
   recomputed and a final Stop worth +10.
5. `Trainer`: the rollout (20 steps of all agents, forward passes with autograd, one backward per
   rollout), the IL and TSE passes, validation on fixed episodes, and the checkpoint (model,
   optimiser, every RNG, every agent's episode and LSTM state, the co-visibility counts): a run killed
   at any moment resumes from `last.pt` exactly as if it had never stopped.
6. `learn`: the loop, `metrics.csv`, progress lines, `last.pt` / `best.pt` (best validation SR).
A trained checkpoint becomes a plugin policy in the next stage, kgnavbench/policy.py.
"""

from __future__ import annotations

import ast
import csv
import dataclasses
import hashlib
import io
import json
import math
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import claims, encoder, models
from .env import SUCCESS_RULES, TRAINING_MAX_STEPS, reward
from .files import atomic_write, first_line, git_revision
from .kitchens import KITCHEN_NAMES, check_name
from .plugins import load_plugin
from .tasks import (
    MIN_START_DISTANCE,
    STOP,
    load_task_file,
    optimal_action_mask,
    shortest_trajectory,
    walk_back_trajectory,
)
from .vecenv import CURRICULUM_REACH, Navigators, StateSpace, arrays_state, build_space, load_arrays

CHECKPOINT_FORMAT = 1
VALIDATION_CAP = 1000  # validation kitchens are unseen kitchens: evaluate's cap of 1000 actions
EXPERTS = ("walk_back", "shortest", "dagger")
METRICS = (
    "frames",
    "seconds",
    "frames_per_s",
    "updates",
    "episodes",
    "mean_reward",
    "mean_return",
    "success_rate",
    "rl_loss",
    "il_loss",
    "tse_loss",
    "val_sr",
    "val_spl",
)


class TrainError(ValueError):
    """Bad training input or state: a bad option, a run directory holding another config, a corrupt
    checkpoint. Reported as one line."""


# ------------------------------------------------------------------------------------------------
# 1. Options and runs


@dataclass
class TrainOptions:
    """Options every learned method shares (`--set key=value`). A plugin's Config extends this."""

    success_rule: str = "destination"  # the paper's: Stop at the destination; "visible": SAVN's
    # Training episodes treat a wrong Stop as a no-op (evaluation ends the episode). Ending them from
    # the start, stopping at once (-0.01) beats every walk that does not reach the destination, and a
    # policy that has never succeeded learns just that (measured: SR 0 after 750k frames in
    # FloorPlan1). `stop_ends_from=N` ends them from frame N on, a curriculum; measured in FloorPlan1
    # with N = 1M, the training SR fell from 95% to under 1% within 750k frames of the switch. With
    # start_curriculum (below) the agents succeed from the first updates, and N = 0 works.
    stop_ends_from: int | None = None
    # ... and costs this much more than a step (the paper's rewards otherwise): without it the agent
    # learns that a wrong Stop costs no more than a move, Stops often, and evaluation punishes that
    wrong_stop_penalty: float = 0.0
    # actions per training episode (the task's 5000); shorter episodes mean more of them per frame
    episode_cap: int = TRAINING_MAX_STEPS
    # a curriculum on start distance over this fraction of the run's frames: training episodes start
    # as near the destination as a start can be (no receptacle open, pitch 0), then ever farther (a
    # distance drawn uniformly from 0 to a reach that grows linearly to CURRICULUM_REACH actions; the
    # nearest start below it where none lies at it), then from the training starts as usual. Without
    # imitation the agents otherwise meet too few successes to learn from in a short run: a
    # destination is one state of thousands (measured, 20 kitchens, 2M frames, lstm_a3c with
    # stop_ends_from=0 and episode_cap=200: seen/seen SR 0 without, 8.6 / 7.6% with 1.0). 0 = off
    start_curriculum: float = 0.0
    agents_per_kitchen: int = 64  # agents per training kitchen, all stepped at once
    # each agent keeps one training target (agent j of a kitchen: its target j mod the kitchen's
    # targets), as the paper's "140 threads, each thread learns for a different target"; false: every
    # episode draws a target of the agent's kitchen
    fixed_targets: bool = True
    n_steps: int = 20  # rollout length: n-step returns
    lr: float = 7e-4  # Adam
    gamma: float = 0.99
    value_weight: float = 0.5  # alpha: weight of the value loss
    entropy: float = 0.01  # weight of the entropy bonus
    max_grad_norm: float = 10.0
    # bfloat16 autocast (CPU). Off by default: on a CPU without native bf16 (no AVX512-BF16 or AMX;
    # torch.ops.mkldnn._is_mkldnn_bf16_supported() is False on the 2-core development machine) autocast's
    # bf16 products run in ATen's reference kernels (measured there, kg_attention il+tse, 140 agents,
    # 2 threads, under load from another process: 421 frames/s with bf16, 4,878 without)
    bf16: bool = False
    hidden: int = 256  # siamese / fusion width
    lstm: int = 256
    # imitation learning: cross-entropy on expert trajectories
    il: bool = False
    # "walk_back": the paper's expert, "only one expert trajectory for each training target": from the
    # destination, MoveBack, else MoveLeft, else RotateRight, for a walk of random length, reversed;
    # "shortest": one BFS-optimal path per target from a training start; "dagger": the BFS-optimal
    # actions of every state the agents visit (DAgger with a privileged shortest-path teacher, not the
    # paper's IL: it learns far more, e.g. 91% seen/seen SR against the paper's 8%)
    il_expert: str = "walk_back"
    il_walk: int = 25  # the walk back is 10..il_walk steps long (drawn per target), as the training starts
    il_frames: int = 2_000_000  # IL is mixed into the loss until this many frames ("online")
    il_batch: int = 32  # expert trajectories per update
    il_weight: float = 1.0
    # target skill extension: relabelled sub-trajectories of the agents' own episodes
    tse: bool = False
    tse_subtargets: int = 5  # per episode, sampled at random among the states that show a novel object
    # the seen kitchens' unseen targets may be sub-targets (the paper's "TSE (targets)"): this trains on
    # the seen-kitchens/unseen-targets column's test targets, so it is off by default ("TSE (seen targets)")
    tse_unseen_targets: bool = False
    tse_window: int = 40  # steps before the sub-target that are relabelled
    tse_batch: int = 64  # sub-trajectories per update
    # measured in FloorPlan1 (lstm_a3c il=true tse=true, 3M frames): at 1.0 the relabelled "Stop
    # here, +10" episodes outweighed the rest and the agents learned to Stop anywhere (evaluation SR 0)
    tse_weight: float = 0.1
    # truncated importance weights min(1, pi/mu) on the relabelled steps. Without them every action of a
    # relabel (mostly ending in +10) is pushed up whatever the current policy thinks of it, and the
    # policy collapses onto its own habits. Measured, 20 kitchens, 80 agents, 2M frames, seen/seen SR
    # static / actionable without -> with: +TSE (with start_curriculum) 0.0 / 0.0 -> 9.9 / 6.8,
    # +IL+TSE 21.0 / 17.8 -> 62.3 / 62.7, +KG+Attention 73.5 / 77.1 -> 43.2 / 31.4 (one seed each)
    tse_importance: bool = True
    # a wrong Stop in a sub-target's window is an episode of the relabelled task too, one that failed:
    # "Stop here, short of the sub-target" (-0.01, no +10) trains beside the successful relabel. Without
    # these the relabels only ever reward Stop, and since training's wrong Stop is a no-op the agents
    # learned to Stop everywhere (measured, 20 kitchens, 2M frames: lstm_a3c tse=true ended its
    # evaluation episodes after ~6 actions, SR 0)
    tse_failures: bool = True
    # logs, checkpoints, validation
    log_every: int = 200_000  # frames between metrics rows (and checkpoints)
    val_every: int = 1_000_000  # frames between validations (and at the end)
    val_kitchens: int = 5  # the first N validation kitchens
    val_episodes: int = 5  # the first N fixed episodes per target
    threads: int = 2
    # end to end from pixels: the encoder CNN (from the committed weights) trains with the policy on
    # the 84x84 views instead of reading cached features (the GPU path; slow on a CPU)
    pixels: bool = False

    def __post_init__(self) -> None:
        self.check()  # a bad option fails when the config is made, before a run directory exists

    def check(self) -> None:
        if self.success_rule not in SUCCESS_RULES:
            raise TrainError(f"success_rule must be one of {SUCCESS_RULES}, not {self.success_rule!r}")
        if self.il_expert not in EXPERTS:
            raise TrainError(f"il_expert must be one of {EXPERTS}, not {self.il_expert!r}")
        positive = (
            "episode_cap agents_per_kitchen n_steps hidden lstm il_batch tse_window tse_batch log_every "
            "val_every val_kitchens val_episodes threads il_walk"
        )
        for name in positive.split():
            if getattr(self, name) < 1:
                raise TrainError(f"{name} must be at least 1, not {getattr(self, name)}")
        if not (0 < self.gamma <= 1 and self.lr > 0 and self.max_grad_norm > 0):
            raise TrainError("need 0 < gamma <= 1, lr > 0 and max_grad_norm > 0")
        if min(self.tse_subtargets, self.il_frames, self.stop_ends_from or 0) < 0:
            raise TrainError("tse_subtargets, il_frames and stop_ends_from must not be negative")
        if not 0 <= self.start_curriculum <= 1:
            raise TrainError(
                f"start_curriculum is a fraction of the run, 0 to 1, not {self.start_curriculum}"
            )


@dataclass(frozen=True)
class Run:
    """Where and how long a plugin's `train` hook trains."""

    directory: Path
    method: str
    frames: int
    seed: int
    kitchens: tuple[str, ...]  # training kitchens (their seen targets only)
    progress: Callable[[str], None] = print


def training_kitchens(kitchens=()) -> tuple[str, ...]:
    """The training kitchens to train on: all of the split, or the given ones (each must be one)."""
    train = load_task_file()["splits"]["train"]
    if not kitchens:
        return tuple(sorted(train, key=KITCHEN_NAMES.index))
    for k in kitchens:
        check_name(k)
        if k not in train:
            raise TrainError(f"{k} is not a training kitchen (training kitchens: {', '.join(train)})")
    return tuple(dict.fromkeys(kitchens))


# the library code that decides a run's numbers besides the plugin: the training starts and the state
# graphs' semantics, the env's rewards, the models and this trainer (kitchens, world and render reach a
# run through the state-graph cache, which is keyed by their own fingerprint)
TRAINING_CODE = ("tasks.py", "encoder.py", "env.py", "vecenv.py", "models.py", "train.py")


def training_code_sha256(package: Path = Path(__file__).parent) -> str:
    """A hash of the training code's syntax trees without docstrings, so that a finished run is not
    reused after a change to how runs train, while comments, docstrings and formatting do not count."""
    digest = hashlib.sha256()
    for name in TRAINING_CODE:
        tree = ast.parse((package / name).read_text(), filename=name)
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (
                isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
        digest.update(f"{name}\0{ast.dump(tree)}\0".encode())
    return digest.hexdigest()


def run_record(plugin, config, frames: int, seed: int, kitchens: tuple[str, ...]) -> dict:
    """What decides a run: its hash names the run directory."""
    return {
        "method": plugin.name,
        "options": json.loads(json.dumps(asdict(config))),
        "plugin_source_sha256": hashlib.sha256(plugin.source_bytes()).hexdigest(),
        "training_code_sha256": training_code_sha256(),
        "frames": frames,
        "seed": seed,
        "kitchens": list(kitchens),
    }


def run_directory(runs_dir: Path | str, record: dict) -> Path:
    digest = hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:10]
    return Path(runs_dir) / "train" / f"{record['method']}-{digest}"


def train_method(
    method: str,
    options: dict[str, str] | None = None,
    frames: int = 10_000_000,
    seed: int = 0,
    kitchens=(),
    runs_dir: Path | str = "runs",
    progress: Callable[[str], None] = print,
) -> Path:
    """Train METHOD (or resume its run, or find it finished) and return the run directory."""
    plugin = load_plugin(method)
    hook = getattr(plugin.module, "train", None)
    if not callable(hook):
        raise TrainError(f"{method} does not train: {plugin.source} defines no train(config, run)")
    if frames < 1:
        raise TrainError(f"frames must be positive, not {frames}")
    config = plugin.config(options or {})
    kitchens = training_kitchens(kitchens)
    record = run_record(plugin, config, frames, seed, kitchens)
    directory = run_directory(runs_dir, record)
    if (directory / "finished.json").exists():
        progress(f"{directory} is a finished run of {frames:,} frames; nothing to do")
        return directory
    # one trainer per run directory: a second one started on it at once is refused (a killed one's
    # claim is stale and taken over by the resume)
    try:
        with claims.held(directory / "trainer.claim", f"run {directory}"):
            return _train_in(
                directory, hook, config, record, Run(directory, method, frames, seed, kitchens, progress)
            )
    except claims.ClaimError as e:
        raise TrainError(str(e)) from e


def _train_in(directory: Path, hook, config, record: dict, run: Run) -> Path:
    if (directory / "finished.json").exists():  # finished by the process that held the claim before us
        run.progress(f"{directory} is a finished run of {run.frames:,} frames; nothing to do")
        return directory
    config_path = directory / "config.json"
    if config_path.exists():
        try:
            old = json.loads(config_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise TrainError(f"{config_path} is unreadable ({e}); delete {directory} to start over") from e
        old_record = {k: v for k, v in old.items() if k != "git_revision"}
        if old_record != record:
            differ = sorted(k for k in set(record) | set(old_record) if record.get(k) != old_record.get(k))
            raise TrainError(
                f"{directory} holds a run with another config (differs in {', '.join(differ)}); "
                "refusing to resume it: delete it or use another --runs folder"
            )
    else:
        atomic_write(config_path, json.dumps({**record, "git_revision": git_revision()}, indent=2) + "\n")
    hook(config, run)
    return directory


def n_step_returns(rewards: torch.Tensor, dones: torch.Tensor, bootstrap: torch.Tensor, gamma: float):
    """(T, B) rewards and done flags (the episode ended at that step), (B,) value of the state after
    the last step: R_t = r_t + gamma * R_{t+1} * (1 - done_t), R_T = bootstrap."""
    returns = torch.empty_like(rewards)
    running = bootstrap
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + gamma * running * (1.0 - dones[t])
        returns[t] = running
    return returns


def actor_critic_loss(
    log_prob: torch.Tensor,
    value: torch.Tensor,
    entropy: torch.Tensor,
    returns: torch.Tensor,
    value_weight: float,
    entropy_weight: float,
    weights: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict]:
    """A3C's loss over any batch of (taken action's log-prob, value, entropy, return): policy gradient
    with advantage R - V (weighted per sample by `weights`: TSE's importance weights), value loss
    0.5 (R - V)^2 with weight alpha, minus the entropy bonus; `mask` drops padding."""
    mask = torch.ones_like(value) if mask is None else mask
    weights = torch.ones_like(value) if weights is None else weights
    n = mask.sum().clamp(min=1.0)
    advantage = (returns - value).detach()
    policy = -(weights * log_prob * advantage * mask).sum() / n
    value_loss = 0.5 * (((returns - value) ** 2) * mask).sum() / n
    bonus = (entropy * mask).sum() / n
    loss = policy + value_weight * value_loss - entropy_weight * bonus
    return loss, {"policy": policy.item(), "value": value_loss.item(), "entropy": bonus.item()}


def optimal_actions(
    space: StateSpace, targets: np.ndarray, states: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """On-policy IL's labels: for each agent the set of BFS-optimal actions (B, 10) — every action
    one step nearer the goal, or Stop on it — and whether the goal is reachable at all (B,). All of
    them, not one: BFS ties are common (a strafe or a turn), and a single tie-broken label asks the
    network to learn the tie-break."""
    now = space.dist[targets, states]
    return optimal_action_mask(now, space.dist[targets[:, None], space.next_state[states]]), now >= 0


def optimal_action_loss(log_p: torch.Tensor, optimal: np.ndarray, known: np.ndarray) -> torch.Tensor:
    """-log of the probability the policy gives to the optimal actions (B,), zero where unknown."""
    mask = torch.from_numpy(optimal)
    total = torch.logsumexp(log_p.masked_fill(~mask, float("-inf")), -1)
    return -torch.where(torch.from_numpy(known), total, torch.zeros_like(total))


def imitation_loss(logits: torch.Tensor, actions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the expert's actions, padding masked out."""
    ce = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), actions.reshape(-1), reduction="none")
    return (ce * mask.reshape(-1)).sum() / mask.sum().clamp(min=1.0)


# ------------------------------------------------------------------------------------------------
# 4. IL data and TSE relabelling


@dataclass
class Sequences:
    """Padded sequences for a separate pass of the model: states[i, t] where actions[i, t] is taken,
    toward the goal state goal[i] (whose view is the target image)."""

    states: np.ndarray  # (N, L) global states
    actions: np.ndarray  # (N, L)
    mask: np.ndarray  # (N, L) bool, False on padding
    goal: np.ndarray  # (N,) global state: the target image's state
    rewards: np.ndarray | None = None  # (N, L)
    behaviour: np.ndarray | None = None  # (N, L) behaviour policy's probability (NaN: not taken by it)


def pad(seqs: list[tuple[list[int], list[int]]], goals, extra=None) -> Sequences:
    n, length = len(seqs), max(len(a) for _, a in seqs)
    states = np.zeros((n, length), np.int64)
    actions = np.zeros((n, length), np.int64)
    mask = np.zeros((n, length), bool)
    for i, (s, a) in enumerate(seqs):
        states[i, : len(s)], actions[i, : len(a)], mask[i, : len(a)] = s, a, True
        states[i, len(s) :] = s[-1]
    return Sequences(states, actions, mask, np.asarray(goals, np.int64), **(extra or {}))


def expert_sequences(space: StateSpace, expert: str, walk: int, rng: np.random.Generator) -> Sequences:
    """One expert trajectory per target of the space: the paper's walk-back from the destination (a
    walk of 10..`walk` steps, its length drawn by rng: "to a random start"; reversed), or the
    BFS-optimal path from a training start drawn by rng."""
    seqs = []
    for r in range(len(space.target_ids)):
        k = space.target_kitchen[r]
        off, kt = space.offsets[k], space.tasks[k]
        dest = int(space.destination[r])
        if expert == "walk_back":
            steps = int(rng.integers(min(MIN_START_DISTANCE, walk), walk + 1))
            start, actions = walk_back_trajectory(kt.graph, dest - off, steps)
            start += off
        else:
            lo, hi = space.start_ptr[r], space.start_ptr[r + 1]
            start = int(space.start_flat[lo + rng.integers(hi - lo)])
            actions = shortest_trajectory(space.next_state, space.dist[r], start)
        states = [int(start)]
        for a in actions[:-1]:
            states.append(int(space.next_state[states[-1], a]))
        if not space.goal[r, states[-1]]:
            raise TrainError(f"the {expert} expert of {space.target_ids[r]} does not end at its destination")
        seqs.append((states, actions))
    return pad(seqs, space.destination)


def assign_targets(space: StateSpace, kitchen: np.ndarray) -> np.ndarray:
    """One training target per agent, as the paper's threads: the j-th agent of a kitchen trains its
    kitchen's target j mod (targets of the kitchen). Every target needs an agent."""
    kitchen = np.asarray(kitchen, np.int64)
    assigned = np.empty(len(kitchen), np.int64)
    for k in range(len(space.kitchens)):
        rows = space.kitchen_rows[space.kitchen_ptr[k] : space.kitchen_ptr[k + 1]]
        agents = np.flatnonzero(kitchen == k)
        if len(agents) < len(rows):
            raise TrainError(
                f"{space.kitchens[k]} has {len(rows)} training targets but {len(agents)} agents: with "
                f"fixed_targets each target needs an agent (set agents_per_kitchen to at least {len(rows)}, "
                "or fixed_targets=false)"
            )
        assigned[agents] = rows[np.arange(len(agents)) % len(rows)]
    return assigned


def subtarget_types(space: StateSpace) -> np.ndarray:
    """(T, 125) per training target, the object types whose sight makes a state one of TSE's
    sub-targets for an agent training that target: novel objects (`tse_types`) and the kitchen's other
    training targets ("the targets trained by other threads"), never its own target's type."""
    n_types = space.objects.shape[1]
    own = np.zeros((len(space.kitchens), n_types), bool)
    own[space.target_kitchen, space.target_type] = True
    eligible = space.tse_types[space.target_kitchen] | own[space.target_kitchen]
    eligible[np.arange(len(space.target_ids)), space.target_type] = False
    return eligible


class SubtargetSampler:
    """TSE's sub-targets, sampled as the paper: per agent and episode, `k` of the steps that reached a
    state showing a sub-target object (`subtarget_types`), drawn uniformly at random among all such
    steps of the episode (reservoir sampling, Algorithm R, so the whole episode need not be kept).
    Each kept step is stored with the window of at most `window` steps of its episode that led to it;
    `finish` hands an ended episode's samples over for relabelling. Its arrays are its state."""

    FIELDS = ("ring_state", "ring_action", "ring_prob", "episode_tick", "count", "slot_state",
              "slot_action", "slot_prob", "slot_length", "slot_goal")  # fmt: skip

    def __init__(self, n_agents: int, k: int, window: int):
        self.k, self.window = k, window
        shape = (n_agents, window)
        # the last `window` steps of every agent (column tick % window): state before, action, its prob
        self.ring_state = np.zeros(shape, np.int64)
        self.ring_action = np.zeros(shape, np.int64)
        self.ring_prob = np.zeros(shape, np.float64)
        self.episode_tick = np.zeros(n_agents, np.int64)  # the tick of the episode's first step
        self.count = np.zeros(n_agents, np.int64)  # sub-target steps met in this episode
        self.slot_state = np.zeros((n_agents, k, window), np.int64)  # chronological, right-aligned
        self.slot_action = np.zeros((n_agents, k, window), np.int64)
        self.slot_prob = np.zeros((n_agents, k, window), np.float64)
        self.slot_length = np.zeros((n_agents, k), np.int64)
        self.slot_goal = np.zeros((n_agents, k), np.int64)

    def step(self, tick, before, actions, probs, after, candidate, rng: np.random.Generator) -> None:
        """Record one step of every agent; `candidate` marks the agents whose step reached a state
        showing a sub-target object (a Stop reaches nothing new: the caller leaves Stops out)."""
        column = tick % self.window
        self.ring_state[:, column], self.ring_action[:, column], self.ring_prob[:, column] = (
            before,
            actions,
            probs,
        )
        idx = np.flatnonzero(candidate)
        if not len(idx) or not self.k:
            return
        self.count[idx] += 1
        m = self.count[idx]
        # Algorithm R: the m-th candidate fills slot m-1 while there is one, else replaces a random
        # slot with probability k/m
        slot = np.where(m <= self.k, m - 1, rng.integers(0, m))
        keep = slot < self.k
        idx, slot = idx[keep], slot[keep]
        if not len(idx):
            return
        length = np.minimum(self.window, tick - self.episode_tick[idx] + 1)
        columns = (tick - self.window + 1 + np.arange(self.window)) % self.window
        self.slot_state[idx, slot] = self.ring_state[idx][:, columns]
        self.slot_action[idx, slot] = self.ring_action[idx][:, columns]
        self.slot_prob[idx, slot] = self.ring_prob[idx][:, columns]
        self.slot_length[idx, slot] = length
        self.slot_goal[idx, slot] = after[idx]

    def finish(self, idx: np.ndarray, next_tick: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
        """The sampled windows (states, actions, behaviour probs, sub-target state) of the agents
        whose episodes ended; their next episodes start at `next_tick` with nothing sampled."""
        out = []
        for i in idx:
            for j in range(min(int(self.count[i]), self.k)):
                n = int(self.slot_length[i, j])
                out.append(
                    (
                        self.slot_state[i, j, -n:].copy(),
                        self.slot_action[i, j, -n:].copy(),
                        self.slot_prob[i, j, -n:].copy(),
                        int(self.slot_goal[i, j]),
                    )
                )
        self.count[idx] = 0
        self.episode_tick[idx] = next_tick
        return out

    def state_dict(self) -> dict:
        return arrays_state(self, self.FIELDS)

    def load_state_dict(self, d: dict) -> None:
        load_arrays(self, self.FIELDS, d, "TSE's")


def relabel(states, actions, behaviour, goal: int) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """HER-style: a walk states[0] -a0-> states[1] ... -a_{m-1}-> states[m] == goal becomes the task
    "reach goal and Stop": the same actions plus a final Stop at goal, rewards recomputed with the
    env's reward function (goal = that one state), the Stop succeeding (+10). Returns states (m + 1),
    actions (m + 1), rewards (m + 1) and the behaviour probabilities (NaN for the added Stop)."""
    states, actions = [int(s) for s in states], [int(a) for a in actions]
    if states[-1] != goal or len(states) != len(actions) + 1:
        raise ValueError("relabel needs states[0..m] ending at the goal and m actions")
    after = np.array(states[1:] + [goal])
    on_goal = after == goal
    reached_before = np.concatenate([[states[0] == goal], np.logical_or.accumulate(on_goal)[:-1]])
    success = np.zeros(len(after), bool)
    success[-1] = True
    rewards = reward(on_goal & ~reached_before, success)
    return states, actions + [STOP], rewards, np.append(np.asarray(behaviour, np.float64), np.nan)


# ------------------------------------------------------------------------------------------------
# 5. The trainer


def _detach(hidden):
    return None if hidden is None else tuple(h.detach() for h in hidden)


def _rows(hidden, idx):
    return None if hidden is None else tuple(h[idx] for h in hidden)


def _keep(hidden, keep: torch.Tensor):
    return None if hidden is None else tuple(h * keep.view(-1, *([1] * (h.dim() - 1))) for h in hidden)


class Model:
    """The actor-critic with what it needs around it: features and object vectors of a state space,
    the knowledge graph, frame histories (FF) and scene ids."""

    def __init__(self, net, config: models.ModelConfig, covis, bf16: bool):
        self.net, self.config, self.covis, self.bf16 = net, config, covis, bf16
        self.uses_graph = config.kg != "none" and config.kg_graph == "accumulated"

    def adjacency(self) -> torch.Tensor | None:
        if not self.uses_graph:
            return None
        return torch.as_tensor(np.asarray(self.covis.adjacency()), dtype=torch.float32)

    def graph(self):
        """The knowledge graph's per-update terms (models.GraphTerms), computed once for all the steps
        that share these weights and this adjacency; None without an accumulated graph."""
        adjacency = self.adjacency()
        if adjacency is None:
            return None
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            return self.net.graph_terms(adjacency)

    def inputs(self, space: StateSpace, states, goals, history=None):
        """The network's inputs for agents in `states` (or their frame `history` (..., H) for FF)
        toward the target images of `goals` (states): view features (or views), each distinct target's
        features (or view) once with the row of every agent's (None for FF: one per agent), and the
        visible-type vectors R_t and R_g. Any leading shape (B or T x B)."""
        s = torch.from_numpy(np.ascontiguousarray(states))
        g = torch.from_numpy(np.ascontiguousarray(goals))
        target_rows = None
        if self.config.arch == "lstm":
            distinct, rows = np.unique(goals, return_inverse=True)
            target_rows = torch.from_numpy(rows.reshape(-1))
        else:
            distinct = goals
        if self.config.pixels:
            view = torch.from_numpy(space.views[history if history is not None else states])
            target = torch.from_numpy(space.views[distinct])
        else:
            view = space.features_t[torch.from_numpy(history) if history is not None else s]
            target = space.features_t[torch.from_numpy(np.ascontiguousarray(distinct))]
        return view, target, target_rows, space.objects_t[s], space.objects_t[g]

    def __call__(self, space: StateSpace, states, goals, hidden, graph, scene=None, history=None):
        """One forward pass: agents in `states` (or their frame `history` (B, H) for FF) toward the
        target images of `goals` (states); `graph`: the knowledge graph's terms (`Model.graph`)."""
        view, target, target_rows, r_t, r_g = self.inputs(space, states, goals, history)
        return self.forward(view, target, target_rows, r_t, r_g, hidden, graph, scene)

    def forward(self, view, target, target_rows, r_t, r_g, hidden, graph, scene=None):
        """One forward pass on the network's inputs themselves (as `inputs` gives them; the evaluation
        policy builds them from the env's observations); scene: (B,) training-kitchen indices (FF)."""
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            logits, value, hidden, extras = self.net(
                view,
                target,
                r_t,
                r_g,
                hidden,
                adjacency=graph,
                scene=None if scene is None else torch.from_numpy(np.ascontiguousarray(scene)),
                target_rows=target_rows,
            )
        return logits.float(), value.float(), hidden, extras

    def unroll(self, space: StateSpace, states, goals, hidden, keep, graph, scene=None, history=None):
        """The network over T steps of B agents at once, for learning: states and goals (T, B) (FF:
        history (T, B, H)), the LSTM state before the first step, keep (T, B) 0 where an episode ended
        at that step (the state is zeroed after it; None: no ends). The parts that do not recur run
        once over all T x B rows, only the LSTM cell steps through time. -> logits (T, B, 10), values
        (T, B)."""
        n, b = states.shape
        flat = history.reshape(n * b, -1) if history is not None else None
        view, target, target_rows, r_t, r_g = self.inputs(space, states.reshape(-1), goals.reshape(-1), flat)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
            joint, _ = self.net.encode(view, target, r_t, r_g, graph, target_rows)
            if self.config.arch != "lstm":
                scenes = torch.from_numpy(np.ascontiguousarray(np.tile(scene, n)))
                logits, values, _ = self.net.act(joint, None, scenes)
            else:
                joint = joint.view(n, b, -1)
                outputs = []
                for t in range(n):
                    hidden = self.net.recur(joint[t], hidden)
                    outputs.append(hidden[0])
                    if keep is not None:
                        hidden = _keep(hidden, keep[t])
                logits, values = self.net.heads(torch.stack(outputs))
        return logits.float().view(n, b, -1), values.float().view(n, b)


class Trainer:
    """A2C over all training kitchens at once, with optional IL and TSE; its whole state checkpoints."""

    def __init__(self, run: Run, options: TrainOptions, model_config: models.ModelConfig, rl: bool):
        self.run, self.opts, self.rl = run, options, rl
        self.kitchens = list(run.kitchens)
        self.model_config = dataclasses.replace(model_config, n_scenes=len(self.kitchens))
        self.ff = self.model_config.arch == "ff"
        self.space = build_space(
            self.kitchens, "seen", options.success_rule, self.model_config.pixels, options.tse_unseen_targets
        )
        # seeded after build_space: encoding features on a cache miss draws from torch's generator
        torch.manual_seed(run.seed)
        net = models.make_model(self.model_config)
        if net.encoder is not None:  # end to end: start from the committed encoder and its statistics
            net.encoder.load_state_dict(encoder.load_encoder().state_dict())
            stats = encoder.encoder_feature_stats()
            net.feature_mean.copy_(stats["mean"])
            net.feature_std.copy_(stats["std"])
        self.model = Model(net, self.model_config, models.CoVisibility(), options.bf16)
        self.optimizer = torch.optim.Adam(net.parameters(), lr=options.lr)
        self.rng = np.random.default_rng(run.seed)
        self.generator = torch.Generator().manual_seed(run.seed)
        # training draws nothing from Python's `random`, but a checkpoint saves its state: seeded, two
        # identical runs write identical checkpoints (and a plugin that uses it stays reproducible)
        random.seed(run.seed)
        self.frames = self.updates = 0
        self.best_val_sr = -1.0
        self.stats = self._empty_stats()
        self.val_space: StateSpace | None = None
        n_agents = options.agents_per_kitchen * len(self.kitchens)
        kitchen = np.repeat(np.arange(len(self.kitchens)), options.agents_per_kitchen)
        self.nav = Navigators(
            self.space,
            kitchen,
            stop_ends=options.stop_ends_from == 0,
            assigned=assign_targets(self.space, kitchen) if options.fixed_targets else None,
        )
        self.cap = options.episode_cap
        self.nav.draw(np.arange(n_agents), self.rng, self.cap, self.reach())
        self.hidden = net.initial_state(n_agents)
        self.history = np.repeat(self.nav.state[:, None], self.model_config.history, 1) if self.ff else None
        # TSE: the sub-targets sampled per episode, and the windows of the episodes that ended during
        # this rollout, relabelled by the update that follows it
        self.tick = 0  # steps of the run (every agent steps at each tick)
        self.tse = SubtargetSampler(n_agents, options.tse_subtargets, options.tse_window)
        self.subtarget_types = subtarget_types(self.space)
        self.tse_windows: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.il = options.il or not rl
        self.dagger = self.il and options.il_expert == "dagger"
        self.experts = (
            expert_sequences(
                self.space, options.il_expert, options.il_walk, np.random.default_rng([run.seed, 1])
            )
            if self.il and not self.dagger
            else None
        )

    @staticmethod
    def _empty_stats() -> dict:
        keys = (
            "frames", "reward", "episodes", "successes", "returns", "rl", "il", "tse",
            "losses_rl", "losses_il", "losses_tse",
        )  # fmt: skip
        return dict.fromkeys(keys, 0.0)

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> None:
        """One rollout of every agent (or, IL only, one expert batch) and one gradient step."""
        graph = self.model.graph()
        loss = torch.zeros(())
        imitate = self.il and (not self.rl or self.frames < self.opts.il_frames)
        self.nav.stop_ends = self.opts.stop_ends_from is not None and self.frames >= self.opts.stop_ends_from
        if self.rl or self.dagger:
            rl_loss, il_loss = self.rollout(graph, imitate and self.dagger)
            if self.rl:
                loss = loss + rl_loss
                self.stats["rl"] += rl_loss.item()
                self.stats["losses_rl"] += 1
            if il_loss is not None:
                loss = loss + self.opts.il_weight * il_loss
                self.stats["il"] += il_loss.item()
                self.stats["losses_il"] += 1
        if imitate and not self.dagger:
            il_loss, n_frames = self.imitation(graph)
            loss = loss + self.opts.il_weight * il_loss
            self.stats["il"] += il_loss.item()
            self.stats["losses_il"] += 1
            if not self.rl:
                self.frames += n_frames
                self.stats["frames"] += n_frames
        if self.rl and self.opts.tse:
            tse_loss = self.skill_extension(graph)
            if tse_loss is not None:
                loss = loss + self.opts.tse_weight * tse_loss
                self.stats["tse"] += tse_loss.item()
                self.stats["losses_tse"] += 1
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.net.parameters(), self.opts.max_grad_norm)
        self.optimizer.step()
        self.updates += 1

    def rollout(self, graph, imitate: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """n steps of every agent, then the learning pass over them; returns the A2C loss of the
        rollout and, when `imitate`, the cross-entropy of the teacher's actions on every visited state
        (DAgger). The steps run without autograd (acting needs no graph); `Model.unroll` then replays
        the same states with autograd, the non-recurrent layers once for all n x B rows, which costs
        far fewer small operations than a graph built step by step."""
        opts, nav, space = self.opts, self.nav, self.space
        n, b = opts.n_steps, nav.n
        states = np.zeros((n, b), np.int64)
        targets = np.zeros((n, b), np.int64)
        actions = np.zeros((n, b), np.int64)
        reached = np.zeros((n, b), np.int64)  # the state each step reached (before a new episode began)
        histories = np.zeros((n, b, self.model_config.history), np.int64) if self.ff else None
        rewards = np.zeros((n, b), np.float32)
        dones = np.zeros((n, b), np.float32)
        start_hidden = hidden = _detach(self.hidden)
        scene = nav.kitchen if self.ff else None
        with torch.no_grad():
            for t in range(n):
                states[t], targets[t] = nav.state, nav.target
                if self.ff:
                    histories[t] = self.history
                goals = space.destination[nav.target]
                logits, _, hidden, _ = self.model(space, nav.state, goals, hidden, graph, scene, self.history)
                probs = F.softmax(logits, -1)
                action = torch.multinomial(probs, 1, generator=self.generator).squeeze(1)
                a = action.numpy()
                actions[t] = a
                before = nav.state.copy()
                r, terminated, truncated = nav.step(a)
                reached[t] = nav.state
                if opts.wrong_stop_penalty:
                    r = r - opts.wrong_stop_penalty * ((a == STOP) & ~nav.success)
                done = terminated | truncated
                rewards[t], dones[t] = r, done
                if opts.tse:
                    candidate = (a != STOP) & (
                        space.objects[nav.state] & self.subtarget_types[nav.target]
                    ).any(1)
                    taken = probs.gather(1, action[:, None]).squeeze(1).numpy()
                    self.tse.step(self.tick, before, a, taken, nav.state, candidate, self.rng)
                self.tick += 1
                finished = np.flatnonzero(done)
                if len(finished):
                    self.stats["episodes"] += len(finished)
                    self.stats["successes"] += int(nav.success[finished].sum())
                    self.stats["returns"] += float(nav.episode_return[finished].sum())
                    self._new_episodes(finished)
                hidden = _keep(hidden, torch.from_numpy(~done).float())
                if self.ff:
                    self.history = np.concatenate([self.history[:, 1:], nav.state[:, None]], 1)
                    self.history[finished] = nav.state[finished, None]
            goals = space.destination[nav.target]
            _, bootstrap, _, _ = self.model(space, nav.state, goals, hidden, graph, scene, self.history)
        self.hidden = hidden
        if self.model.uses_graph:
            self.model.covis.add(space.objects[reached.reshape(-1)])
        self.frames += n * b
        self.stats["frames"] += n * b
        self.stats["reward"] += float(rewards.sum())
        # the learning pass: the same n steps again, with autograd
        keep = torch.from_numpy(1.0 - dones)
        logits, values = self.model.unroll(
            space, states, space.destination[targets], start_hidden, keep, graph, scene, histories
        )
        log_p = F.log_softmax(logits, -1)
        taken = log_p.gather(2, torch.from_numpy(actions)[..., None]).squeeze(2)
        entropies = -(log_p.exp() * log_p).sum(-1)
        returns = n_step_returns(torch.from_numpy(rewards), torch.from_numpy(dones), bootstrap, opts.gamma)
        loss, _ = actor_critic_loss(taken, values, entropies, returns, opts.value_weight, opts.entropy)
        il = None
        if imitate:
            optimal, known = optimal_actions(space, targets.reshape(-1), states.reshape(-1))
            il = optimal_action_loss(log_p.reshape(n * b, -1), optimal, known).mean()
        return loss, il

    def reach(self) -> int | None:
        """The curriculum's farthest start (actions from the destination) at this frame; None: off or over."""
        n = self.opts.start_curriculum * self.run.frames
        if not n or self.frames >= n:
            return None
        return int(CURRICULUM_REACH * self.frames / n)

    def _new_episodes(self, idx: np.ndarray) -> None:
        if self.opts.tse:  # the ended episodes' sub-targets, for this update's relabelling
            self.tse_windows += self.tse.finish(idx, self.tick)
        self.nav.draw(idx, self.rng, self.cap, self.reach())

    def subtrajectories(self) -> Sequences | None:
        """Up to tse_batch of the sub-targets sampled in the episodes that ended during this rollout,
        relabelled; the rest are dropped."""
        windows, self.tse_windows = self.tse_windows, []
        if not windows:
            return None
        take = self.rng.choice(len(windows), min(self.opts.tse_batch, len(windows)), replace=False)
        seqs, goals, rewards, behaviour = [], [], [], []
        for j in sorted(take):
            states, actions, probs, goal = windows[j]
            # the relabelled episode starts after the window's last Stop: in the task "reach the
            # sub-target and Stop" that Stop ended the episode (a failure), so the walk after it is
            # the whole episode; keeping it would reward a wrong Stop with the sub-target's +10. The
            # failure itself (tse_failures) is a one-step episode: Stop where it stopped, -0.01.
            # (Only where training's wrong Stop is a no-op: where it ends the episode, no window holds one.)
            stops = np.flatnonzero(actions == STOP)
            if len(stops):
                last = stops[-1]
                if self.opts.tse_failures and states[last] != goal:
                    seqs.append(([int(states[last])], [STOP]))
                    goals.append(goal)
                    rewards.append(reward(np.zeros(1, bool), np.zeros(1, bool)))
                    behaviour.append(probs[last : last + 1].astype(np.float64))
                states, actions, probs = states[last + 1 :], actions[last + 1 :], probs[last + 1 :]
            if len(actions) == 0:
                continue
            s, a, r, mu = relabel(list(states) + [goal], actions, probs, goal)
            seqs.append((s, a))
            goals.append(goal)
            rewards.append(r)
            behaviour.append(mu)
        if not seqs:
            return None
        seq = pad(seqs, goals)
        seq.rewards = np.zeros(seq.states.shape, np.float32)
        seq.behaviour = np.full(seq.states.shape, np.nan)
        for i, (r, mu) in enumerate(zip(rewards, behaviour)):
            seq.rewards[i, : len(r)], seq.behaviour[i, : len(mu)] = r, mu
        return seq

    def sequence_pass(self, seq: Sequences, graph):
        """A separate pass of the model over padded sequences from a zero state: logits (L, N, 10),
        values (L, N)."""
        n, length = seq.states.shape
        states = np.ascontiguousarray(seq.states.T)
        goals = np.broadcast_to(seq.goal, (length, n))
        history = None
        if self.ff:  # the last `history` states of each step, the first state repeated before it
            back = np.arange(length)[:, None] - np.arange(self.model_config.history)[::-1]
            history = np.ascontiguousarray(np.transpose(seq.states[:, np.clip(back, 0, None)], (1, 0, 2)))
        scene = self.space.kitchen_of[seq.states[:, 0]] if self.ff else None
        hidden = self.model.net.initial_state(n)
        return self.model.unroll(self.space, states, goals, hidden, None, graph, scene, history)

    def imitation(self, graph) -> tuple[torch.Tensor, int]:
        """Cross-entropy on il_batch expert trajectories drawn at random."""
        ex = self.experts
        n = len(ex.goal)
        take = torch.randperm(n, generator=self.generator)[: min(self.opts.il_batch, n)].sort().values.numpy()
        seq = Sequences(ex.states[take], ex.actions[take], ex.mask[take], ex.goal[take])
        last = int(seq.mask.sum(1).max())
        seq = Sequences(seq.states[:, :last], seq.actions[:, :last], seq.mask[:, :last], seq.goal)
        logits, _ = self.sequence_pass(seq, graph)
        mask = torch.from_numpy(seq.mask.T.astype(np.float32))
        return imitation_loss(logits, torch.from_numpy(seq.actions.T.copy()), mask), int(seq.mask.sum())

    def skill_extension(self, graph) -> torch.Tensor | None:
        """A2C's loss on this rollout's relabelled sub-trajectories (whole episodes: Monte-Carlo
        returns), optionally with truncated importance weights min(1, pi/mu)."""
        seq = self.subtrajectories()
        if seq is None:
            return None
        logits, values = self.sequence_pass(seq, graph)
        log_p = F.log_softmax(logits, -1)
        actions = torch.from_numpy(seq.actions.T.copy())
        taken = log_p.gather(2, actions[..., None]).squeeze(2)
        entropy = -(log_p.exp() * log_p).sum(-1)
        mask = torch.from_numpy(seq.mask.T.astype(np.float32))
        rewards = torch.from_numpy(seq.rewards.T.copy())
        dones = torch.zeros_like(rewards)
        dones[torch.from_numpy(seq.mask.sum(1) - 1), torch.arange(len(seq.goal))] = 1.0
        returns = n_step_returns(rewards, dones, torch.zeros(len(seq.goal)), self.opts.gamma)
        weights = None
        if self.opts.tse_importance:
            mu = torch.from_numpy(seq.behaviour.T.copy()).float()
            ratio = (taken.detach().exp() / mu).clamp(max=1.0)
            weights = torch.where(torch.isnan(mu), torch.ones_like(ratio), ratio)
        loss, _ = actor_critic_loss(
            taken, values, entropy, returns, self.opts.value_weight, self.opts.entropy, weights, mask
        )
        return loss

    # -- validation ------------------------------------------------------------------------------
    def validate(self) -> tuple[float, float, int]:
        """SR and SPL (percent) on the validation kitchens' fixed episodes (the first val_episodes per
        target), cap 1000, under the success rule; its own seeded sampling, so training is untouched."""
        if self.val_space is None:
            names = load_task_file()["splits"]["val"][: self.opts.val_kitchens]
            self.val_space = build_space(
                sorted(names, key=KITCHEN_NAMES.index),
                "all",
                self.opts.success_rule,
                self.model_config.pixels,
            )
        sp = self.val_space
        rows = [(r, s) for r, starts in enumerate(sp.fixed_starts) for s in starts[: self.opts.val_episodes]]
        targets = np.array([r for r, _ in rows], np.int64)
        starts = np.array([s for _, s in rows], np.int64)
        return run_episodes(self.model, sp, targets, starts, VALIDATION_CAP, self.run.seed)

    # -- checkpoints -----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "method": self.run.method,
            "options": asdict(self.opts),
            "model_config": asdict(self.model_config),
            "kitchens": self.kitchens,
            "seed": self.run.seed,
            "frames": self.frames,
            "updates": self.updates,
            "tick": self.tick,
            "best_val_sr": float(self.best_val_sr),
            "stats": {k: float(v) for k, v in self.stats.items()},
            "model": self.model.net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "covis": self.model.covis.state_dict(),
            "rng": {
                "numpy": json.dumps(self.rng.bit_generator.state),  # plain data: weights_only loads it
                "sampling": self.generator.get_state(),
                "torch": torch.get_rng_state(),
                "python": random.getstate(),
            },
            "agents": self.nav.state_dict(),
            "hidden": self.hidden,
            "history": None if self.history is None else torch.from_numpy(self.history.copy()),
            "tse": self.tse.state_dict(),
        }

    def load_state_dict(self, ck: dict) -> None:
        self.model.net.load_state_dict(ck["model"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self.model.covis.load_state_dict(ck["covis"])
        self.rng.bit_generator.state = json.loads(ck["rng"]["numpy"])
        self.generator.set_state(ck["rng"]["sampling"])
        torch.set_rng_state(ck["rng"]["torch"])
        random.setstate(ck["rng"]["python"])
        self.nav.load_state_dict(ck["agents"])
        self.hidden = ck["hidden"]
        self.history = None if ck["history"] is None else ck["history"].numpy().copy()
        self.tse.load_state_dict(ck["tse"])
        self.frames, self.updates, self.tick = ck["frames"], ck["updates"], ck["tick"]
        self.best_val_sr, self.stats = ck["best_val_sr"], dict(ck["stats"])


def run_episodes(model: Model, space: StateSpace, targets, starts, cap: int, seed: int):
    """Run fixed episodes (target rows, start states) to the end with the model's sampled actions;
    returns SR and SPL in percent and the frames taken. FF's scene-specific layers: the first training
    kitchen's (the validation kitchens have none of their own)."""
    n = len(targets)
    nav = Navigators(space, space.target_kitchen[targets])
    nav.begin(np.arange(n), targets, starts, cap)
    generator = torch.Generator().manual_seed(seed)
    hidden = model.net.initial_state(n)
    ff = model.config.arch == "ff"
    history = np.repeat(starts[:, None], model.config.history, 1) if ff else None
    scene = np.zeros(n, np.int64)
    live = np.ones(n, bool)
    frames = 0
    with torch.no_grad():
        graph = model.graph()
        while live.any():
            idx = np.flatnonzero(live)
            goals = space.destination[nav.target[idx]]
            logits, _, rows, _ = model(
                space,
                nav.state[idx],
                goals,
                _rows(hidden, idx),
                graph,
                scene[idx] if ff else None,
                history[idx] if ff else None,
            )
            action = torch.multinomial(F.softmax(logits, -1), 1, generator=generator).squeeze(1).numpy()
            if hidden is not None:
                for h, r in zip(hidden, rows):
                    h[idx] = r
            _, terminated, truncated = nav.step(action, idx)
            if ff:
                history[idx] = np.concatenate([history[idx, 1:], nav.state[idx, None]], 1)
            live[idx[terminated | truncated]] = False
            frames += len(idx)
    shortest = space.dist[targets, starts]
    spl = nav.success * shortest / np.maximum(np.maximum(nav.path, shortest), 1)
    return float(100.0 * nav.success.mean()), float(100.0 * spl.mean()), frames


# ------------------------------------------------------------------------------------------------
# 6. The loop: logs, checkpoints, resumption


def save_checkpoint(path: Path, state: dict) -> None:
    def write(f) -> None:
        buffer = io.BytesIO()
        torch.save(state, buffer)
        f.write(buffer.getvalue())

    atomic_write(path, write)


def load_checkpoint(path: Path | str) -> dict:
    """A checkpoint written by `learn`; anything else is a TrainError naming the file."""
    path = Path(path)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
            raise ValueError("not a kgnavbench checkpoint")
        for key in ("model", "model_config", "covis", "kitchens", "frames"):
            if key not in ck:
                raise ValueError(f"no {key!r}")
        return ck
    except FileNotFoundError as e:
        raise TrainError(f"checkpoint {path} does not exist") from e
    except Exception as e:  # noqa: BLE001 - whatever is wrong with the file, one line naming it
        raise TrainError(
            f"checkpoint {path} is corrupt ({type(e).__name__}: {first_line(e)}); delete it to start over"
        ) from e


def _read_metrics(path: Path, up_to: int) -> list[dict]:
    """The rows of metrics.csv up to a frame count (a resumed run drops what it will redo)."""
    if not path.exists():
        return []
    rows = []
    for row in csv.DictReader(path.read_text().splitlines()):
        try:
            if int(row["frames"]) <= up_to and None not in row.values():
                rows.append(row)
        except (KeyError, TypeError, ValueError):
            continue
    return rows


def _csv_text(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, METRICS)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def learn(run: Run, options: TrainOptions, model_config: models.ModelConfig, rl: bool = True) -> Path:
    """Train (or resume) a run: A2C (rl=True) with IL and TSE as the options say, or IL alone."""
    options.check()
    torch.set_num_threads(options.threads)
    progress = run.progress
    trainer = Trainer(run, options, model_config, rl)
    last, best = run.directory / "last.pt", run.directory / "best.pt"
    metrics_path = run.directory / "metrics.csv"
    if last.exists():
        ck = load_checkpoint(last)
        if ck["options"] != asdict(options) or ck["model_config"] != asdict(trainer.model_config):
            raise TrainError(f"{last} was trained with another config; delete {run.directory} to start over")
        try:
            trainer.load_state_dict(ck)
        except (KeyError, ValueError, RuntimeError, TypeError) as e:
            raise TrainError(f"checkpoint {last} does not fit this run ({type(e).__name__}: {e})") from e
        progress(f"resumed {run.directory} from {last.name} at {trainer.frames:,} frames")
    rows = _read_metrics(metrics_path, trainer.frames)
    atomic_write(metrics_path, _csv_text(rows))
    every = options.log_every
    next_log = (trainer.frames // every + 1) * every
    next_val = (trainer.frames // options.val_every + 1) * options.val_every
    agents = trainer.nav.n if rl or trainer.dagger else 0
    progress(
        f"training {run.method} on {len(trainer.kitchens)} kitchens "
        f"({len(trainer.space.target_ids)} targets, "
        f"{agents} agents) to {run.frames:,} frames; run {run.directory}"
    )
    t0, f0 = time.perf_counter(), trainer.frames
    while trainer.frames < run.frames:
        trainer.update()
        done = trainer.frames >= run.frames
        if trainer.frames < next_log and not done:
            continue
        next_log = (trainer.frames // every + 1) * every
        val_sr = val_spl = float("nan")
        if trainer.frames >= next_val or done:
            next_val = (trainer.frames // options.val_every + 1) * options.val_every
            tv = time.perf_counter()
            val_sr, val_spl, val_frames = trainer.validate()
            progress(
                f"  validation: SR {val_sr:.1f}%, SPL {val_spl:.1f}% ({val_frames:,} frames in "
                f"{time.perf_counter() - tv:.1f} s)"
            )
            if val_sr >= trainer.best_val_sr:  # on a tie the later, longer-trained checkpoint
                trainer.best_val_sr = val_sr
                save_checkpoint(best, {**trainer.state_dict(), "val_sr": val_sr, "val_spl": val_spl})
        row = _metrics_row(trainer, time.perf_counter() - t0, trainer.frames - f0, val_sr, val_spl)
        with open(metrics_path, "a") as f:
            csv.DictWriter(f, METRICS).writerow(row)
        trainer.stats = trainer._empty_stats()
        save_checkpoint(last, trainer.state_dict())
        progress(
            f"{trainer.frames:>12,} frames  {row['frames_per_s']:>8} frames/s  "
            f"reward/frame {row['mean_reward']}  "
            f"SR(train episodes) {row['success_rate']}%  losses RL {row['rl_loss']} IL {row['il_loss']} "
            f"TSE {row['tse_loss']}"
        )
    seconds = time.perf_counter() - t0
    atomic_write(
        run.directory / "finished.json",
        json.dumps({"frames": trainer.frames, "best_val_sr": trainer.best_val_sr, "seconds": seconds}) + "\n",
    )
    progress(
        f"finished {run.method}: {trainer.frames:,} frames, best validation SR {trainer.best_val_sr:.1f}%"
    )
    return run.directory


def _metrics_row(trainer: Trainer, seconds: float, frames_done: int, val_sr: float, val_spl: float) -> dict:
    s = trainer.stats

    def mean(total: str, count: str) -> str:
        return f"{s[total] / s[count]:.4f}" if s[count] else ""

    return {
        "frames": trainer.frames,
        "seconds": f"{seconds:.1f}",
        "frames_per_s": f"{frames_done / max(seconds, 1e-9):.0f}",
        "updates": trainer.updates,
        "episodes": int(s["episodes"]),
        "mean_reward": mean("reward", "frames"),
        "mean_return": mean("returns", "episodes"),
        "success_rate": f"{100 * s['successes'] / s['episodes']:.2f}" if s["episodes"] else "",
        "rl_loss": mean("rl", "losses_rl"),
        "il_loss": mean("il", "losses_il"),
        "tse_loss": mean("tse", "losses_tse"),
        "val_sr": "" if math.isnan(val_sr) else f"{val_sr:.2f}",
        "val_spl": "" if math.isnan(val_spl) else f"{val_spl:.2f}",
    }
