"""Stage 9 — evaluate: the protocol. Fixed episodes through the environment, per-episode results,
and the metrics of Table I.

Columns of Table I (DESIGN.md):
  * seen kitchens / seen targets      training kitchens, training targets; episode cap 100
  * seen kitchens / unseen targets    training kitchens, held-out targets; cap 1000
  * unseen kitchens                   test kitchens, every target; cap 1000
each for static and actionable targets. Validation kitchens are evaluated only on request (`--split
val`, for checkpoint selection).

Metrics per column and kind:
  * SR: the share of successful episodes;
  * SPL: mean of S * L / max(P, L), with S success, L the shortest path from the start (under the
    success rule in force), P the agent's path length in actions, Stop not counted;
  * the same two over episodes whose shortest path is at least 5 actions ("L>=5");
  * collisions per episode (failed moves); the share of episodes whose last view shows the target;
    the mean episode length in actions (Stop counted).

Every episode of a kitchen runs in one env reset per target: 100 agents, one per fixed episode, so
each reset replays exactly the same starts for every method.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import subprocess
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .env import SUCCESS_RULES, parallel_env
from .kitchens import KITCHEN_NAMES, check_name, write_atomic
from .plugins import PluginError, PolicySpec, load_plugin
from .tasks import EPISODES_PER_TARGET, KitchenTasks, load_task_file, load_tasks

COLUMNS = ("seen_seen", "seen_unseen", "unseen_kitchens")
COLUMN_TITLES = {
    "seen_seen": "seen kitchens / seen targets",
    "seen_unseen": "seen kitchens / unseen targets",
    "unseen_kitchens": "unseen kitchens",
    "validation": "validation kitchens",
}
KINDS = ("static", "actionable")
SEEN_CAP, UNSEEN_CAP = 100, 1000
LONG_PATH = 5
SPLITS = ("table", "train", "val", "test")
RESULT_FIELDS = (
    "kitchen",
    "target",
    "kind",
    "column",
    "start",
    "max_steps",
    "success",
    "path_length",
    "shortest_path",
    "collisions",
    "last_view_shows_target",
    "episode_length",
)


class EvalError(ValueError):
    """Bad evaluation input: unknown split or kitchen, a corrupt results file."""


# ------------------------------------------------------------------------------------------------
# The protocol


def column_of(split: str, seen: bool) -> str:
    if split == "train":
        return "seen_seen" if seen else "seen_unseen"
    if split == "test":
        return "unseen_kitchens"
    return "validation"


def episode_cap(column: str) -> int:
    """100 actions for seen kitchens and seen targets; 1000 where the target or kitchen is unseen."""
    return SEEN_CAP if column == "seen_seen" else UNSEEN_CAP


def split_kitchens(split: str) -> list[str]:
    """The kitchens an evaluation covers: 'table' = train + test (Table I), or one split."""
    splits = load_task_file()["splits"]
    if split == "table":
        names = splits["train"] + splits["test"]
    elif split in splits:
        names = splits[split]
    else:
        raise EvalError(f"unknown split {split!r}; choose one of {SPLITS}")
    return sorted(names, key=KITCHEN_NAMES.index)


@dataclass(frozen=True)
class EvalConfig:
    """Everything that decides an evaluation's numbers; its hash names the run directory."""

    method: str
    options: tuple[tuple[str, str], ...] = ()
    success_rule: str = "visible"
    stop_ends: bool = True
    split: str = "table"
    kitchens: tuple[str, ...] = ()  # empty: every kitchen of the split
    episodes_per_target: int = EPISODES_PER_TARGET
    seed: int = 0

    def __post_init__(self) -> None:
        if self.success_rule not in SUCCESS_RULES:
            raise EvalError(f"unknown success rule {self.success_rule!r}; choose one of {SUCCESS_RULES}")
        if self.split not in SPLITS:
            raise EvalError(f"unknown split {self.split!r}; choose one of {SPLITS}")
        if not 1 <= self.episodes_per_target <= EPISODES_PER_TARGET:
            raise EvalError(
                f"episodes per target must be 1..{EPISODES_PER_TARGET}, not {self.episodes_per_target}"
            )
        for k in self.kitchens:
            check_name(k)

    def kitchen_list(self) -> list[str]:
        return list(self.kitchens) if self.kitchens else split_kitchens(self.split)

    def run_name(self) -> str:
        """Deterministic: the method, the rules and a hash of the whole config."""
        digest = hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:8]
        stop = "stop-ends" if self.stop_ends else "stop-noop"
        return f"{self.method}-{self.success_rule}-{stop}-{self.split}-{digest}"


@dataclass(frozen=True)
class EpisodeResult:
    kitchen: str
    target: str
    kind: str
    column: str
    start: int
    max_steps: int
    success: bool
    path_length: int
    shortest_path: int
    collisions: int
    last_view_shows_target: bool
    episode_length: int


def kitchen_episodes(tasks: KitchenTasks, per_target: int) -> list[tuple[str, list[dict]]]:
    """(column, episodes) per target: the first `per_target` fixed starts with the column's cap."""
    out = []
    for t in tasks.targets:
        column = column_of(tasks.split, t.seen)
        cap = episode_cap(column)
        episodes = [{"target": t.object_id, "start": s, "max_steps": cap} for s in t.starts[:per_target]]
        out.append((column, episodes))
    return out


def evaluate_kitchen(plugin, plugin_config, config: EvalConfig, kitchen: str) -> list[EpisodeResult]:
    """Every fixed episode of one kitchen, one env reset per target (an agent per episode)."""
    tasks = load_tasks(kitchen)
    seed = config.seed * 1000 + KITCHEN_NAMES.index(kitchen)  # the same per kitchen, resumable
    policy = plugin.make_policy(plugin_config, PolicySpec.default(seed, tasks.graph.views.shape[1]))
    env = parallel_env(
        kitchen=kitchen,
        n_agents=config.episodes_per_target,
        targets="all",
        success_rule=config.success_rule,
        stop_ends=config.stop_ends,
        tasks=tasks,
    )
    results = []
    for column, episodes in kitchen_episodes(tasks, config.episodes_per_target):
        observations, infos = env.reset(options={"episodes": episodes})
        for agent in env.agents:
            policy.reset(agent)
        start = {agent: e["start"] for agent, e in zip(env.agents, episodes)}
        finished: dict[str, EpisodeResult] = {}
        while env.agents:
            shown = infos if plugin.privileged else _without_expert(infos)
            actions = policy.act(observations, shown)
            _check_actions(plugin, actions, env.agents)
            observations, _, terminations, truncations, infos = env.step(actions)
            for agent in list(observations):
                if terminations[agent] or truncations[agent]:
                    i = infos[agent]
                    finished[agent] = EpisodeResult(
                        kitchen=kitchen,
                        target=i["target"],
                        kind=i["target_kind"],
                        column=column,
                        start=start[agent],
                        max_steps=episodes[0]["max_steps"],
                        success=i["success"],
                        path_length=i["path_length"],
                        shortest_path=i["shortest_path"],
                        collisions=i["collisions"],
                        last_view_shows_target=i["last_view_shows_target"],
                        episode_length=i["episode_length"],
                    )
                    del observations[agent], infos[agent]
        results.extend(finished[agent] for agent in start)  # in episode order, not finishing order
    return results


def _without_expert(infos: dict) -> dict:
    return {a: {k: v for k, v in i.items() if k != "expert_action"} for a, i in infos.items()}


def _check_actions(plugin, actions, agents) -> None:
    if not isinstance(actions, dict) or set(agents) - set(actions):
        missing = sorted(set(agents) - set(actions)) if isinstance(actions, dict) else agents
        raise PluginError(f"{plugin.source}: act() must return an action for every agent; missing {missing}")


# ------------------------------------------------------------------------------------------------
# Metrics


@dataclass(frozen=True)
class Metrics:
    episodes: int
    sr: float  # percent
    spl: float  # percent
    episodes_long: int  # shortest path >= LONG_PATH
    sr_long: float
    spl_long: float
    collisions: float  # per episode
    last_view_shows_target: float  # percent
    episode_length: float


def spl_term(r) -> float:
    """S * L / max(P, L) for one episode (L = P = 0 cannot happen: starts never show the target)."""
    if not r.success:
        return 0.0
    return r.shortest_path / max(r.path_length, r.shortest_path, 1)


def metrics(results: list) -> Metrics:
    n = len(results)
    long = [r for r in results if r.shortest_path >= LONG_PATH]

    def pct(values) -> float:
        values = list(values)
        return 100.0 * sum(values) / len(values) if values else float("nan")

    def mean(values) -> float:
        values = list(values)
        return sum(values) / len(values) if values else float("nan")

    return Metrics(
        episodes=n,
        sr=pct(r.success for r in results),
        spl=pct(spl_term(r) for r in results),
        episodes_long=len(long),
        sr_long=pct(r.success for r in long),
        spl_long=pct(spl_term(r) for r in long),
        collisions=mean(r.collisions for r in results),
        last_view_shows_target=pct(r.last_view_shows_target for r in results),
        episode_length=mean(r.episode_length for r in results),
    )


def summarize(results: list) -> dict[tuple[str, str], Metrics]:
    """Metrics per (column, kind), plus (column, 'all') and ('all', 'all')."""
    groups: dict[tuple[str, str], list] = {}
    for r in results:
        for key in ((r.column, r.kind), (r.column, "all"), ("all", "all")):
            groups.setdefault(key, []).append(r)
    order = [*COLUMNS, "validation", "all"]
    keys = sorted(groups, key=lambda k: (order.index(k[0]), (*KINDS, "all").index(k[1])))
    return {k: metrics(groups[k]) for k in keys}


def format_summary(summary: dict[tuple[str, str], Metrics], title: str) -> str:
    """The Table I layout for one method: a row per column and kind."""
    head = [
        "column",
        "kind",
        "episodes",
        "SR",
        "SPL",
        "SR L>=5",
        "SPL L>=5",
        "collisions",
        "last view",
        "length",
    ]
    rows = []
    for (column, kind), m in summary.items():
        rows.append(
            [
                COLUMN_TITLES.get(column, "all columns"),
                kind,
                f"{m.episodes}",
                f"{m.sr:.2f}",
                f"{m.spl:.2f}",
                f"{m.sr_long:.2f}",
                f"{m.spl_long:.2f}",
                f"{m.collisions:.2f}",
                f"{m.last_view_shows_target:.2f}",
                f"{m.episode_length:.1f}",
            ]
        )
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [title, "| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |"]
    lines.append("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        cells = [c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
# Runs on disk: config with git revision, per-kitchen results (resumable), summary


def git_revision() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=10,
        )
        rev = out.stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return (rev + ("-dirty" if dirty else "")) if rev else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def write_atomic_text(path: Path, text: str) -> None:
    write_atomic(path, text.encode())


def read_results(path: Path) -> list[EpisodeResult]:
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        return [EpisodeResult(**{k: row[k] for k in RESULT_FIELDS}) for row in rows]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise EvalError(
            f"results file {path} is corrupt ({type(e).__name__}: {e}); delete it to rerun"
        ) from e


@dataclass
class EvalRun:
    config: EvalConfig
    directory: Path
    results: list[EpisodeResult] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
    steps: int = 0
    resumed: list[str] = field(default_factory=list)


def evaluate(config: EvalConfig, runs_dir: Path | str = "runs", progress=print) -> EvalRun:
    """Run (or resume) an evaluation. Each finished kitchen's results are saved atomically in
    RUN/episodes/<kitchen>.jsonl; a rerun of the same config skips kitchens already there."""
    plugin = load_plugin(config.method)
    plugin_config = plugin.config(dict(config.options))
    kitchens = config.kitchen_list()
    directory = Path(runs_dir) / "eval" / config.run_name()
    saved = {
        "config": json.loads(json.dumps(asdict(config))),  # as it reads back (tuples are lists)
        "plugin_config": dataclasses.asdict(plugin_config),
        "plugin_source": plugin.source,
        "git_revision": git_revision(),
    }
    config_path = directory / "config.json"
    if config_path.exists():
        try:
            old = json.loads(config_path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise EvalError(f"{config_path} is corrupt ({e}); delete the run directory to start over") from e
        if old.get("config") != saved["config"]:
            raise EvalError(f"{directory} holds another evaluation's results")
    write_atomic_text(config_path, json.dumps(saved, indent=2) + "\n")

    run = EvalRun(config, directory)
    start = time.perf_counter()
    for k, kitchen in enumerate(kitchens):
        path = directory / "episodes" / f"{kitchen}.jsonl"
        if path.exists():
            results = read_results(path)
            run.resumed.append(kitchen)
        else:
            t0 = time.perf_counter()
            results = evaluate_kitchen(plugin, plugin_config, config, kitchen)
            text = "".join(json.dumps(asdict(r)) + "\n" for r in results)
            write_atomic_text(path, text)
            steps = sum(r.episode_length for r in results)
            run.steps += steps
            dt = time.perf_counter() - t0
            progress(
                f"[{k + 1}/{len(kitchens)}] {kitchen}: {len(results)} episodes, "
                f"SR {100 * sum(r.success for r in results) / max(len(results), 1):.1f}%, "
                f"{steps} agent-steps in {dt:.1f} s ({steps / max(dt, 1e-9):,.0f} agent-steps/s)"
            )
        run.results.extend(results)
    run.seconds = time.perf_counter() - start
    run.summary = summarize(run.results)
    summary_json = {f"{c}/{k}": asdict(m) for (c, k), m in run.summary.items()}
    write_atomic_text(directory / "summary.json", json.dumps(summary_json, indent=2) + "\n")
    write_atomic_text(directory / "table.md", format_summary(run.summary, describe(config)) + "\n")
    return run


def describe(config: EvalConfig) -> str:
    stop = "Stop ends the episode" if config.stop_ends else "a wrong Stop is a no-op"
    rule = "with the target visible" if config.success_rule == "visible" else "at the destination"
    options = ", ".join(f"{k}={v}" for k, v in config.options)
    return (
        f"{config.method}{f' ({options})' if options else ''} — success: Stop {rule}; {stop}; "
        f"{config.episodes_per_target} episodes per target, split {config.split}"
    )
