"""Stage 23 — evaluate: the protocol. Fixed episodes through the environment, per-episode results,
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
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from . import store
from .archives import (
    PACKED_SUFFIX,
    RESULT_TYPES,
    SPLITS,
    kitchens_of_split,
    pack_evaluation,
    unpack_evaluation,
    write_results_file,
)
from .env import SUCCESS_RULES, parallel_env
from .files import (
    checksum_matches,
    checksum_path,
    duration_text,
    first_line,
)
from .graph import is_cached, state_graph
from .kitchens import KITCHEN_NAMES, check_name
from .metrics import (
    COLUMN_TITLES,
    KINDS,
    LONG_PATH,
    EpisodeResult,
    format_summary,
    summarize,
    summary_as_json,
)
from .plugins import MAX_SEED, UNWEIGHTED_OPTIONS, Plugin, PluginError, PolicySpec, guarded, load_plugin
from .tasks import EPISODES_PER_TARGET, TASKS_FILE, KitchenTasks, load_task_file, load_tasks, outcome
from .weights import (
    CHECKPOINT_MEANING,
    EvalError,
    Weights,
    checkpoint_name,
    freeze_weights,
    read_weights,
    selected_checkpoint,
)
from .world import ACTIONS

SEEN_CAP, UNSEEN_CAP = 100, 1000
# 2: all episodes of a kitchen in one env reset (a policy's random stream differs from format 1's)
EVALUATION_FORMAT = 2
# ------------------------------------------------------------------------------------------------
# The protocol


def column_of(split: str, seen_target: bool) -> str:
    """Table I's column of a target: its kitchen's split and, in a training kitchen, whether it is a
    training (seen) target."""
    if split == "train":
        return "seen_seen" if seen_target else "seen_unseen"
    if split == "test":
        return "unseen_kitchens"
    return "validation"


def episode_cap(column: str) -> int:
    """100 actions for seen kitchens and seen targets; 1000 where the target or kitchen is unseen."""
    return SEEN_CAP if column == "seen_seen" else UNSEEN_CAP


def _check_kitchen_names(names: tuple[str, ...]) -> None:
    """Every name a kitchen's (check_name's error otherwise), none twice."""
    for k in names:
        check_name(k)
    if len(set(names)) != len(names):
        raise EvalError(f"a kitchen is named twice in {','.join(names)}")


@dataclass(frozen=True)
class EvalConfig:
    """Everything that decides an evaluation's numbers; its hash names the run directory."""

    method: str
    options: tuple[tuple[str, str], ...] = ()
    success_rule: str = "destination"  # the paper's: Stop at the destination; "visible": SAVN's
    stop_ends: bool = True
    split: str = "table"
    kitchens: tuple[str, ...] = ()  # empty: every kitchen of the split
    episodes_per_target: int = EPISODES_PER_TARGET
    seed: int = 0
    run: str = ""  # a learned method's training run directory: its best-validation checkpoint is tested
    checkpoint: str = "best"  # which of the run's checkpoints: best.pt (Table I's rule) or last.pt
    device: str = "cpu"  # where a learned policy computes: "cpu" or "cuda" (kgnavbench/device.py)
    # the training kitchens whose unseen targets are evaluated (the seen kitchens / unseen targets
    # column); the others of the evaluation get their seen targets only. Empty: every target.
    unseen_target_kitchens: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        checkpoint_name(self.checkpoint)
        if self.success_rule not in SUCCESS_RULES:
            raise EvalError(f"unknown success rule {self.success_rule!r}; choose one of {SUCCESS_RULES}")
        if self.success_rule == "arrival" and self.stop_ends:
            raise EvalError("the arrival rule makes Stop a no-op: stop_ends must be False (--stop-noop)")
        if self.split not in SPLITS:
            raise EvalError(f"unknown split {self.split!r}; choose one of {SPLITS}")
        if not 1 <= self.episodes_per_target <= EPISODES_PER_TARGET:
            raise EvalError(
                f"episodes per target must be 1..{EPISODES_PER_TARGET}, not {self.episodes_per_target}"
            )
        if not 0 <= self.seed <= MAX_SEED:
            raise EvalError(f"seed must be in 0..{MAX_SEED}, not {self.seed}")
        _check_kitchen_names(self.kitchens)
        outside = [k for k in self.kitchens if k not in kitchens_of_split(self.split)]
        if outside:  # its episodes would be reported under this split's label
            raise EvalError(
                f"{', '.join(outside)} {'is' if len(outside) == 1 else 'are'} not in the {self.split!r} "
                f"split ({', '.join(kitchens_of_split(self.split))})"
            )
        _check_kitchen_names(self.unseen_target_kitchens)
        # in the kitchens' order: the same kitchens listed otherwise are the same evaluation
        ordered = tuple(sorted(self.unseen_target_kitchens, key=KITCHEN_NAMES.index))
        object.__setattr__(self, "unseen_target_kitchens", ordered)
        training = set(kitchens_of_split("train")) & set(self.kitchen_list())
        elsewhere = [k for k in self.unseen_target_kitchens if k not in training]
        if elsewhere:  # only a training kitchen has a seen kitchens / unseen targets column
            raise EvalError(
                f"unseen targets are evaluated in training kitchens only: {', '.join(elsewhere)} "
                f"{'is' if len(elsewhere) == 1 else 'are'} not a training kitchen of this evaluation"
            )

    def seen_targets_only(self, kitchen: str) -> bool:
        """Whether this evaluation runs only the seen targets of `kitchen` (a training kitchen left
        out of `unseen_target_kitchens`)."""
        return (
            bool(self.unseen_target_kitchens)
            and kitchen not in self.unseen_target_kitchens
            and kitchen in kitchens_of_split("train")
        )

    def kitchen_list(self) -> list[str]:
        return list(self.kitchens) if self.kitchens else kitchens_of_split(self.split)

    def run_name(self, identity: dict | None = None) -> str:
        """Deterministic: the method, the rules and a hash of everything that decides the results (the
        `identity` of `run_identity`: this config, the resolved plugin config, the plugin's source, the
        protocol and the task file)."""
        digest = store.digest(identity if identity is not None else asdict(self), 8)
        stop = "stop-ends" if self.stop_ends else "stop-noop"
        return f"{self.method}-{self.success_rule}-{stop}-{self.split}-{digest}"


def kitchen_episodes(tasks: KitchenTasks, per_target: int) -> list[tuple[str, list[dict]]]:
    """(column, episodes) per target: the first `per_target` fixed starts with the column's cap."""
    out = []
    for t in tasks.targets:
        column = column_of(tasks.split, t.seen)
        cap = episode_cap(column)
        episodes = [{"target": t.object_id, "start": s, "max_steps": cap} for s in t.starts[:per_target]]
        out.append((column, episodes))
    return out


def kitchen_seed(seed: int, kitchen: str) -> int:
    """The policy's seed in one kitchen of an evaluation with `seed`: the same per kitchen, whatever
    else is evaluated, so a kitchen's results resume and a recording replays its episodes."""
    return seed * 1000 + KITCHEN_NAMES.index(kitchen)


def evaluate_kitchen(
    plugin,
    plugin_config,
    config: EvalConfig,
    kitchen: str,
    checkpoint: Path | None = None,
    seen_only: bool = False,
) -> list[EpisodeResult]:
    """Every fixed episode of one kitchen at once: one env reset, an agent per episode (each with its
    column's cap), so a batched policy sees them all in one act() call. `checkpoint`: the weights a
    learned policy loads (the evaluation's frozen copy)."""
    tasks = load_tasks(kitchen)
    seed = kitchen_seed(config.seed, kitchen)
    spec = policy_spec(config, seed, tasks.graph.views.shape[1], checkpoint)
    policy = plugin.make_policy(plugin_config, spec)
    seen_only = seen_only or config.seen_targets_only(kitchen)
    columns, episodes = [], []
    for column, target_episodes in kitchen_episodes(tasks, config.episodes_per_target):
        if seen_only and column != "seen_seen":  # (evaluate_policy's targets="seen")
            continue
        columns += [column] * len(target_episodes)
        episodes += target_episodes
    env = parallel_env(
        kitchen=kitchen,
        n_agents=len(episodes),
        targets="all",
        success_rule=config.success_rule,
        stop_ends=config.stop_ends,
        tasks=tasks,
        features=True,  # the encoder's features of the view and target: what learned plugins look at
        privileged=plugin.privileged,  # the state and expert action only for a plugin that says so
    )
    observations, infos = env.reset(options={"episodes": episodes})
    agents = list(env.agents)
    episode_of = {agent: n for n, agent in enumerate(agents)}
    for agent in agents:
        guarded(plugin, "reset()", policy.reset, agent, where=kitchen)
    if callable(getattr(policy, "act_batch", None)):
        return _run_batched(plugin, policy, env, kitchen, columns, episodes)
    finished: dict[str, EpisodeResult] = {}
    step = 0
    while env.agents:
        shown = infos if plugin.privileged else without_privileged(infos)
        step += 1
        where = f"{kitchen}, step {step}"
        actions = guarded(plugin, "act()", policy.act, observations, shown, where=where)
        check_actions(plugin, actions, env.agents)
        observations, _, terminations, truncations, infos = env.step(actions)
        for agent in list(observations):
            if terminations[agent] or truncations[agent]:
                n = episode_of[agent]
                info = infos[agent]
                finished[agent] = episode_result(kitchen, columns[n], episodes[n], info, terminations[agent])
                del observations[agent], infos[agent]
    return [finished[agent] for agent in agents]  # in episode order, not finishing order


def _run_batched(plugin, policy, env, kitchen: str, columns: list[str], episodes: list[dict]) -> list:
    """evaluate_kitchen's loop for a policy with act_batch (the learned ones): the env's arrays instead
    of per-agent dicts, the same agents in the same order, so the same actions and results as act()."""
    results: list[EpisodeResult | None] = [None] * len(episodes)
    live = np.arange(len(env.agents))  # the episode of each agent in env.agents (agent n runs episode n)
    step = 0
    while env.agents:
        agents = env.agents
        shown = env.info_arrays(privileged=plugin.privileged)
        step += 1
        observed = env.observation_arrays()
        where = f"{kitchen}, step {step}"
        actions = guarded(plugin, "act_batch()", policy.act_batch, agents, observed, shown, where=where)
        actions = check_action_array(plugin, actions, len(agents))
        _, terminated, truncated, infos = env.step_arrays(actions)
        ended = terminated | truncated
        for j in np.flatnonzero(ended).tolist():
            n = int(live[j])
            info = {key: column[j] for key, column in infos.items()}
            results[n] = episode_result(kitchen, columns[n], episodes[n], info, bool(terminated[j]))
        live = live[~ended]
    return results


def episode_result(kitchen: str, column: str, episode: dict, info, terminated: bool) -> EpisodeResult:
    """An ended episode's result from the env's infos at its last step (a per-agent dict, or one
    agent's row of the array infos: plain Python values either way, as the results file holds them).
    `terminated`: it ended by the agent's Stop (with stop_ends every Stop ends it), not by its cap."""
    return EpisodeResult(
        kitchen=kitchen,
        target=str(info["target"]),
        kind=str(info["target_kind"]),
        column=column,
        start=episode["start"],
        max_steps=episode["max_steps"],
        success=bool(info["success"]),
        path_length=int(info["path_length"]),
        shortest_path=int(info["shortest_path"]),
        collisions=int(info["collisions"]),
        last_view_shows_target=bool(info["last_view_shows_target"]),
        episode_length=int(info["episode_length"]),
        stopped=bool(terminated),
    )


def check_action_array(plugin: Plugin, actions, n: int) -> np.ndarray:
    """act_batch() must return n integers 0..9, one per agent in order; anything else names the plugin."""
    array = np.asarray(actions)
    if array.shape != (n,) or array.dtype == bool or not np.issubdtype(array.dtype, np.integer):
        raise PluginError(
            f"{plugin.source}: act_batch() must return {n} integer actions, got {array.dtype} {array.shape}"
        )
    if n and not (array.min() >= 0 and array.max() < len(ACTIONS)):
        raise PluginError(f"{plugin.source}: act_batch() returned an action outside 0..{len(ACTIONS) - 1}")
    return array.astype(np.int64)


PRIVILEGED_INFOS = ("state", "expert_action")  # only a plugin with PRIVILEGED = True reads these


def without_privileged(infos: dict) -> dict:
    """The infos a plugin without PRIVILEGED sees: the env's, less the state index and expert action."""
    shown = {}
    for a, i in infos.items():
        shown[a] = i = dict(i)  # a copy: the env's own dict keeps them
        for key in PRIVILEGED_INFOS:
            i.pop(key, None)
    return shown


def policy_spec(config: EvalConfig, seed: int, view_size: int, checkpoint: Path | None = None) -> PolicySpec:
    """What the policy is told before it starts: for a trained method, its checkpoint (`checkpoint`:
    the evaluation's frozen copy of the weights; else the run's selected one)."""
    if checkpoint is None and config.run:
        checkpoint = selected_checkpoint(config.run, config.method, config.checkpoint)
    return PolicySpec.default(seed, view_size, None if checkpoint is None else str(checkpoint), config.device)


def check_actions(plugin: Plugin, actions, agents) -> None:
    """act() must return {agent: integer 0..9} for every live agent; anything else names the plugin."""
    if not isinstance(actions, dict):
        raise PluginError(f"{plugin.source}: act() returned {type(actions).__name__}, not a dict of actions")
    missing = [a for a in agents if a not in actions]
    if missing:
        raise PluginError(f"{plugin.source}: act() must return an action for every agent; missing {missing}")
    given = [actions[a] for a in agents]
    if set(map(type, given)) <= {int} and (not given or 0 <= min(given) <= max(given) < len(ACTIONS)):
        return  # plain ints in range, the usual case, checked at C speed; anything else one by one
    for agent in agents:
        a = actions[agent]
        if isinstance(a, np.ndarray) and a.ndim == 0:
            a = a[()]
        integer = isinstance(a, (int, np.integer)) and not isinstance(a, (bool, np.bool_))
        if not integer or not 0 <= a < len(ACTIONS):
            raise PluginError(
                f"{plugin.source}: act() returned {a!r} for {agent}; "
                f"an action is an integer 0..{len(ACTIONS) - 1}"
            )


# ------------------------------------------------------------------------------------------------
# Runs on disk: config with git revision, per-kitchen results (resumable), summary


def parse_results(text: str, expected: list[tuple[str, int]], kitchen: str) -> list[EpisodeResult]:
    """The results of one kitchen, checked against the fixed episodes it must hold: `expected` is the
    (target, start) of every episode in order. Raises ValueError on a truncated or foreign file, a wrong
    episode count or a wrongly typed field."""
    lines = text.splitlines()
    if not text.endswith("\n") or len(lines) != len(expected):
        raise ValueError(f"{len(lines)} lines for {len(expected)} episodes (truncated or foreign)")
    results = []
    for n, (line, (target, start)) in enumerate(zip(lines, expected), start=1):
        row = json.loads(line)
        if not isinstance(row, dict) or set(row) not in (set(RESULT_TYPES), set(RESULT_TYPES) - {"stopped"}):
            raise ValueError(f"line {n}: fields {sorted(row) if isinstance(row, dict) else row!r}")
        for key, kind in RESULT_TYPES.items():
            if key not in row:
                continue
            value = row[key]
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise ValueError(f"line {n}: {key}={value!r} is not {kind.__name__}")
        if (row["kitchen"], row["target"], row["start"]) != (kitchen, target, start):
            raise ValueError(f"line {n}: episode {row['target']}@{row['start']} is not {target}@{start}")
        if row["kind"] not in KINDS or row["column"] not in COLUMN_TITLES:
            raise ValueError(f"line {n}: kind {row['kind']!r} or column {row['column']!r} is unknown")
        results.append(EpisodeResult(**row))
    return results


def scored_visible(results: list[EpisodeResult]) -> list[EpisodeResult]:
    """An evaluation's episodes, run under the destination rule with Stop ending the episode, scored
    under the visible rule (SAVN's): the same episodes, since the agents see the same things under both
    rules and Stop ends the episode under both. Success is a Stop in a state whose view shows the
    target (`last_view_shows_target`), and the shortest path the visible rule's, from the episode's
    start. (The other way needs the final state, which a result does not hold.) Episodes without
    `stopped` (results written before it was recorded) cannot be scored: an EvalError says so."""
    out, tasks, distances = [], {}, {}  # kitchen -> its tasks (loaded once); (kitchen, target) -> BFS
    for r in results:
        if r.stopped is None:
            raise EvalError(
                f"the results of {r.kitchen} predate the record of whether an episode ended by Stop, so "
                "they cannot be scored under the visible rule; evaluate again in a fresh --runs folder"
            )
        if (r.kitchen, r.target) not in distances:
            if r.kitchen not in tasks:
                tasks[r.kitchen] = load_tasks(r.kitchen)
            kitchen = tasks[r.kitchen]
            target = next(t for t in kitchen.targets if t.object_id == r.target)
            distances[r.kitchen, r.target] = kitchen.distances(target, "visible")
        shortest = int(distances[r.kitchen, r.target][r.start])
        success, _ = outcome("visible", r.stopped, r.last_view_shows_target, stop_ends=True)
        out.append(dataclasses.replace(r, success=bool(success), shortest_path=shortest))
    return out


def expected_episodes(kitchen: str, per_target: int, seen_only: bool = False) -> list[tuple[str, int]]:
    """(target, start) of every fixed episode of a kitchen that an evaluation runs, in order (of its
    seen targets only with `seen_only`)."""
    tasks = load_task_file()["kitchens"][kitchen]
    targets = [t for t in tasks["targets"] if t["seen"] or not seen_only]
    return [(t["object"], s) for t in targets for s in t["starts"][:per_target]]


def run_identity(config: EvalConfig, plugin: Plugin, plugin_config, weights: Weights | None = None) -> dict:
    """Everything that decides an evaluation's numbers; its hash names the run directory. `weights`:
    the tested checkpoint as read once (`read_weights`; read here when not given)."""
    if weights is None and config.run:
        weights = read_weights(config.run, config.method, config.checkpoint)
    return {
        # as it reads back (tuples are lists); where the run lies and which of its checkpoints is
        # tested are not part of it, the tested weights are
        "config": json.loads(
            json.dumps(
                {
                    k: v
                    for k, v in asdict(config).items()
                    if k not in ("run", "checkpoint")
                    # left out when empty (every target): the evaluations from before it keep their names
                    and not (k == "unseen_target_kitchens" and not v)
                }
            )
        ),
        # the tested weights themselves: a retrained run is another evaluation
        "checkpoint_sha256": weights.sha256 if weights else None,
        "plugin_config": json.loads(json.dumps(dataclasses.asdict(plugin_config), default=str)),
        "plugin_source_sha256": hashlib.sha256(plugin.source_bytes()).hexdigest(),
        # a file an option names (a plugin's own weights, a table): its content, so that a file
        # rewritten at the same path is another evaluation, never the old one's results (only where
        # an option names one: other evaluations keep their names)
        **({"option_files_sha256": files} if (files := option_files_sha256(plugin_config)) else {}),
        "protocol": {
            "seen_cap": SEEN_CAP,
            "unseen_cap": UNSEEN_CAP,
            "long_path": LONG_PATH,
            "evaluation_format": EVALUATION_FORMAT,
            "task_file_sha256": hashlib.sha256(TASKS_FILE.read_bytes()).hexdigest(),
        },
    }


def option_files_sha256(plugin_config) -> dict[str, str]:
    """{option: sha256 of the file it names} for every option of the plugin's config whose value is the
    path of an existing file (relative to the working directory, as the plugin would open it)."""
    if not dataclasses.is_dataclass(plugin_config):
        return {}
    out = {}
    for name, value in sorted(dataclasses.asdict(plugin_config).items()):
        if not isinstance(value, (str, Path)) or not str(value) or len(str(value)) > 4096:
            continue
        path = Path(value)
        try:
            if path.is_file():
                out[name] = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError as e:  # named but unreadable: say so rather than hash nothing
            raise EvalError(
                f"option {name}={value!r} names a file that cannot be read: {e.strerror or e}"
            ) from e
    return out


@dataclass
class EvalRun:
    config: EvalConfig
    directory: Path
    results: list[EpisodeResult] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
    steps: int = 0
    resumed: list[str] = field(default_factory=list)


def open_run(directory: Path, identity: dict, plugin: Plugin) -> None:
    """Create the evaluation's directory with its config.json (the identity, the plugin's file, the git
    revision), or check that an existing one holds this evaluation (`store.open_directory`)."""
    recorded = {"plugin_source": plugin.source}
    store.open_directory(directory, identity, EvalError, "an evaluation", under="identity", recorded=recorded)


def check_fixed_options(config: EvalConfig, plugin_config) -> None:
    """A checkpoint fixes the options it was trained with: `eval --run DIR --set k=v` with another value
    would be recorded under the evaluation's name but not used, so it is refused."""
    selected_checkpoint(config.run, config.method, config.checkpoint)  # a run of this method, with it
    if not dataclasses.is_dataclass(plugin_config):
        return
    path = Path(config.run) / "config.json"
    try:
        trained = json.loads(path.read_text()).get("options")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as e:
        raise EvalError(f"--run {config.run}: {path.name} is unreadable ({first_line(e)})") from e
    if not isinstance(trained, dict):
        raise EvalError(f"--run {config.run}: {path.name} holds no table of options (got {trained!r:.40})")
    resolved = json.loads(json.dumps(asdict(plugin_config)))
    differ = [
        k
        for k, _ in config.options
        if k in trained and resolved.get(k) != trained[k] and k not in UNWEIGHTED_OPTIONS
    ]
    if differ:
        given = ", ".join(f"{k}={resolved.get(k)!r}" for k in differ)
        fixed = ", ".join(f"{k}={trained[k]!r}" for k in differ)
        raise EvalError(
            f"--run {config.run} was trained with {fixed}; its checkpoint fixes them (given {given})"
        )


def evaluate(
    config: EvalConfig, runs_dir: Path | str = "runs", progress=print, archive: Path | None = None
) -> EvalRun:
    """Run (or resume) an evaluation. Each finished kitchen's results are saved atomically in
    RUN/episodes/<kitchen>.jsonl; a rerun of the same config skips kitchens already there, after
    checking that they hold exactly the expected episodes (a damaged file is set aside and re-run).
    `archive`: a folder of packed evaluations (tables/episodes/paper): this one, if packed there, is
    unpacked first and so counted, not run again; if not, it is packed there once finished."""
    plugin = load_plugin(config.method)
    plugin_config = plugin.config(dict(config.options))
    if callable(getattr(plugin.module, "train", None)) and not config.run:
        raise EvalError(
            f"{config.method} is a learned method: evaluate a trained run with --run DIR, one shipped in "
            f"zoo/ (zoo/README.md lists them, e.g. --run zoo/{config.method}-<hash>) or one you train "
            f"(`kgnavbench train --method {config.method}` prints its folder)"
        )
    if config.run:
        check_fixed_options(config, plugin_config)
    kitchens = config.kitchen_list()
    weights = read_weights(config.run, config.method, config.checkpoint) if config.run else None
    identity = run_identity(config, plugin, plugin_config, weights)
    directory = Path(runs_dir) / "eval" / config.run_name(identity)
    packed = Path(archive) / f"{directory.name}{PACKED_SUFFIX}" if archive is not None else None
    if packed is not None and packed.is_file():
        unpack_evaluation(packed, directory.parent)  # keeps what is there; refuses another evaluation
    open_run(directory, identity, plugin)
    frozen = freeze_weights(directory, weights) if weights else None

    run = EvalRun(config, directory)
    start = time.perf_counter()
    evaluated, evaluating = 0, 0.0  # kitchens evaluated in this process and their seconds (the ETA)
    expected_of = {
        k: expected_episodes(k, config.episodes_per_target, config.seen_targets_only(k)) for k in kitchens
    }
    todo = [k for k in kitchens if not (directory / "episodes" / f"{k}.jsonl").exists()]
    if todo:  # long work says what it will do; the time per kitchen and an ETA follow each kitchen
        episodes = sum(len(expected_of[k]) for k in todo)
        kept = (
            f" ({len(kitchens) - len(todo)} done before, in {directory})" if len(todo) < len(kitchens) else ""
        )
        progress(f"evaluating {config.method}: {len(todo)} kitchens, {episodes:,} episodes{kept}")
    for k, kitchen in enumerate(kitchens):
        path = directory / "episodes" / f"{kitchen}.jsonl"
        expected = expected_of[kitchen]
        results = None
        if path.exists():
            data = path.read_bytes()
            try:
                if checksum_matches(path, data) is None:  # nothing proves it is what was written
                    raise ValueError(f"its checksum {checksum_path(path).name} is missing")
                results = parse_results(data.decode(), expected, kitchen)
            except (OSError, UnicodeDecodeError, json.JSONDecodeError, ValueError, TypeError) as e:
                aside = path.with_name(f"{path.name}.corrupt-{int(time.time())}")
                path.rename(aside)
                print(
                    f"kgnavbench: {path} is damaged ({e}); moved to {aside.name}, re-running", file=sys.stderr
                )
                results = None
            else:  # well formed: counted only if it is what was written
                if checksum_matches(path, data) is False:
                    raise EvalError(
                        f"{path} does not match its checksum ({checksum_path(path).name}): it changed "
                        "after it was written; refusing to count it (delete both to re-run that kitchen)"
                    )
                run.resumed.append(kitchen)
        if results is None:
            if not is_cached(kitchen):  # built once, and said, so that the speed below is the episodes'
                tb = time.perf_counter()
                progress(f"[{k + 1}/{len(kitchens)}] {kitchen}: building its state graph and views (once)")
                state_graph(kitchen)
                progress(f"[{k + 1}/{len(kitchens)}] {kitchen}: built in {time.perf_counter() - tb:.1f} s")
            t0 = time.perf_counter()
            results = evaluate_kitchen(plugin, plugin_config, config, kitchen, frozen)
            write_results_file(path, "".join(json.dumps(asdict(r)) + "\n" for r in results), checksum=True)
            steps = sum(r.episode_length for r in results)
            run.steps += steps
            dt = time.perf_counter() - t0
            evaluated, evaluating = evaluated + 1, evaluating + dt
            left = len(kitchens) - k - 1
            eta = f", ETA {duration_text(evaluating / evaluated * left)}" if left else ""
            progress(
                f"[{k + 1}/{len(kitchens)}] {kitchen}: {len(results)} episodes, "
                f"SR {100 * sum(r.success for r in results) / max(len(results), 1):.1f}%, "
                f"{steps} agent-steps in {dt:.1f} s ({steps / max(dt, 1e-9):,.0f} agent-steps/s){eta}"
            )
        run.results.extend(results)
    run.seconds = time.perf_counter() - start
    run.summary = summarize(run.results)
    summary_json = summary_as_json(run.summary)
    write_results_file(directory / "summary.json", json.dumps(summary_json, indent=2) + "\n")
    write_results_file(directory / "table.md", format_summary(run.summary, describe(config)) + "\n")
    if packed is not None and not packed.is_file():
        if os.access(packed.parent, os.W_OK | os.X_OK):
            progress(f"packed {directory.name} into {pack_evaluation(directory, packed.parent)}")
        else:  # a read-only checkout's archive: used, never written
            progress(f"not packed: {packed.parent} is read-only ({directory} keeps the evaluation)")
    return run


# What each success rule (tasks.SUCCESS_RULES) is called in every caption, summary and table intro
SUCCESS_RULE_TEXT = {
    "destination": "Stop at the destination",
    "visible": "Stop with the target visible",
    "arrival": "arriving at the destination (Zhu et al.'s rule)",
}


def describe(config: EvalConfig) -> str:
    stop = "Stop ends the episode" if config.stop_ends else "a wrong Stop is a no-op"
    rule = SUCCESS_RULE_TEXT[config.success_rule]
    if config.success_rule == "arrival":
        stop = "Stop is a no-op"
    options = ", ".join(f"{k}={v}" for k, v in config.options)
    return (
        f"{config.method}{f' ({options})' if options else ''} — success: {rule}; {stop}; "
        f"{config.episodes_per_target} episodes per target, split {config.split}"
        + (
            f"; unseen targets in {', '.join(config.unseen_target_kitchens)} only"
            if config.unseen_target_kitchens
            else ""
        )
        + (
            f"; checkpoint {selected_checkpoint(config.run, config.method, config.checkpoint)} "
            f"({CHECKPOINT_MEANING.get(config.checkpoint, 'a snapshot kept with keep_every')})"
            if config.run
            else ""
        )
    )
