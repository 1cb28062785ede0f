"""Stage 35 — figures: the paper's figures from Table I's runs, as PNG drawn with OpenCV
(kgnavbench/plots.py).

`tsne` is exact t-SNE in torch; `attention_figure` shows what an attention vector weighs. `figures` draws
the paper's figures from the table's runs (collisions and last-view rate on unseen kitchens, the t-SNE of
the GCN's node features, training curves); `figures_of_table` from a preset. Bad input (a missing or
unreadable run, too few points) is a FigureError naming it.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from .errors import KgnavbenchError
from .files import atomic_write, first_line
from .plots import (
    INK,
    PALETTE,
    Axes,
    FigureError,
    bar_line_figure,
    curves_figure,
    curves_image,
    draw_legend,
    draw_text,
    new_canvas,
    nice_ticks,
    scatter_figure,
    wrap_text,
    write_png,
)
from .record import read_metrics  # a bad metrics.csv is a RecordError
from .world import ACTIONS

# ------------------------------------------------------------------------------------------------
# t-SNE (van der Maaten & Hinton 2008), exact: O(n^2) memory, meant for the 125 GCN node features


def _conditional_p(d: torch.Tensor, perplexity: float, steps: int = 100) -> torch.Tensor:
    """P(j|i) with each row's Gaussian precision beta found by bisection so that its entropy is
    log(perplexity); all rows at once."""
    n = len(d)
    off = ~torch.eye(n, dtype=torch.bool)
    # shifting a row's distances by its nearest neighbour's leaves P(j|i) unchanged and keeps exp finite
    d = (d - d.masked_fill(~off, math.inf).min(1, keepdim=True).values).masked_fill(~off, 0.0)
    target = math.log(perplexity)
    beta = torch.ones(n, 1, dtype=d.dtype)
    lo = torch.zeros_like(beta)
    hi = torch.full_like(beta, math.inf)
    for _ in range(steps):
        p = torch.exp(-d * beta) * off
        total = p.sum(1, keepdim=True)
        entropy = torch.log(total) + beta * (d * p).sum(1, keepdim=True) / total
        too_wide = entropy > target  # too many neighbours: narrow the Gaussian (raise beta)
        lo = torch.where(too_wide, beta, lo)
        hi = torch.where(too_wide, hi, beta)
        beta = torch.where(torch.isinf(hi), beta * 2, (lo + hi) / 2)
    p = torch.exp(-d * beta) * off
    return p / p.sum(1, keepdim=True)


def tsne(
    x: torch.Tensor, dims: int = 2, perplexity: float = 30.0, iterations: int = 1000, seed: int = 0
) -> torch.Tensor:
    """Embed the rows of x (n, d) in `dims` dimensions. Gradient descent with momentum (0.5, then 0.8)
    and per-parameter gains, early exaggeration 12 over the first quarter (at most 250 iterations), the
    learning rate scikit-learn's "auto" picks. float64 on the CPU: the same seed gives the same result."""
    if x.ndim != 2 or len(x) < 3:
        raise ValueError(f"t-SNE needs a (n, d) matrix with n >= 3, not shape {tuple(x.shape)}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # (n, n) with n ~ 100: handing work to threads costs far more than it saves
    try:
        y = _tsne(x.detach().to("cpu", torch.float64), dims, perplexity, iterations, seed)
    finally:
        torch.set_num_threads(threads)
    return y.to(torch.float32)


def _tsne(x: torch.Tensor, dims: int, perplexity: float, iterations: int, seed: int) -> torch.Tensor:
    """tsne's body on a float64 CPU tensor."""
    n = len(x)
    perplexity = min(float(perplexity), (n - 1) / 3)  # more neighbours than points cannot be matched
    p = _conditional_p(torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist").square(), perplexity)
    p = ((p + p.T) / (2 * n)).clamp_min(1e-12)  # symmetric joint probabilities
    exaggeration, early = 12.0, min(250, iterations // 4)
    rate = max(n / exaggeration / 4, 50.0)
    generator = torch.Generator().manual_seed(seed)
    y = torch.randn(n, dims, generator=generator, dtype=torch.float64) * 1e-2  # N(0, 1e-4 I) as in the paper
    velocity = torch.zeros_like(y)
    gains = torch.ones_like(y)
    for it in range(iterations):
        num = 1.0 / (1.0 + (y[:, None] - y[None]).square().sum(-1))  # Student-t kernel of the embedding
        num.fill_diagonal_(0.0)
        q = (num / num.sum()).clamp_min(1e-12)
        w = ((exaggeration if it < early else 1.0) * p - q) * num
        grad = 4.0 * (w.sum(1, keepdim=True) * y - w @ y)
        # delta-bar-delta gains: a larger step where the last move still goes downhill, smaller elsewhere
        gains = torch.where((grad > 0) != (velocity > 0), gains + 0.2, gains * 0.8).clamp_min(0.01)
        velocity = (0.5 if it < early else 0.8) * velocity - rate * gains * grad
        y = y + velocity
        y = y - y.mean(0)
    return y


# ------------------------------------------------------------------------------------------------
# Figures: PNG with OpenCV, white background, axes with round ticks


ATTENTION_SIZE = (1200, 560)
ATTENTION_BARS = 12  # object types shown, the most attended first
# where an attended type was seen: in the view only, in the target image only, in both, in neither (a
# softmax over all nodes weighs those too); tab10's blue, orange, green and grey, as BGR
ATTENDED_IN = (
    ("in the view", PALETTE[0]),
    ("in the target", PALETTE[1]),
    ("in both", PALETTE[2]),
    ("in neither", PALETTE[7]),
)


def attention_figure(
    view: np.ndarray,
    target: np.ndarray,
    attended: list[tuple[str, float, str]],
    path,
    title: str,
    caption: str,
    size=ATTENTION_SIZE,
) -> Path:
    """The paper's attention example: the agent's view and its target image (RGB, upscaled with
    nearest neighbours, as the network saw them), and beside them the attention weights over object
    types as horizontal bars, the most attended first (at most ATTENTION_BARS), each bar coloured by
    where its type was seen (`attended`: (type, weight, one of ATTENDED_IN's names))."""
    where = dict(ATTENDED_IN)
    if not attended:
        raise FigureError("attention_figure needs at least one attended object type")
    for name, weight, seen_in in attended:
        if seen_in not in where or not math.isfinite(weight):
            raise FigureError(f"attended type {name!r}: weight {weight!r} seen {seen_in!r} cannot be drawn")
    img = new_canvas(title, size)
    width, height = size
    side = 340
    for k, (image, label) in enumerate(((view, "the agent's view"), (target, "the target image"))):
        x0, y0 = 30 + k * (side + 20), 80
        rgb = np.asarray(image, np.uint8)
        img[y0 : y0 + side, x0 : x0 + side] = cv2.resize(
            rgb[:, :, ::-1], (side, side), interpolation=cv2.INTER_NEAREST
        )
        cv2.rectangle(img, (x0 - 1, y0 - 1), (x0 + side, y0 + side), INK, 1)
        draw_text(img, label, (x0 + side // 2, y0 + side + 12), 0.55, align="centre", valign="top")
    shown = sorted(attended, key=lambda a: -a[1])[:ATTENTION_BARS]
    left, right, top = 30 + 2 * (side + 20) + 150, width - 60, 90
    row = min(28, (height - 150 - top) // len(shown))
    ticks = nice_ticks(0.0, max(w for _, w, _ in shown))
    ax = Axes(img, left, top, right, top + row * len(shown), (0.0, ticks[-1]), (0.0, float(len(shown))))
    ax.x_ticks(ticks, "attention weight")
    for i, (name, weight, seen_in) in enumerate(shown):
        y = top + i * row
        x1, _ = ax.px(weight, 0)
        x1 = max(x1, left + 3)  # a weight near 0 still shows its colour
        cv2.rectangle(img, (left, y + 4), (x1, y + row - 4), where[seen_in], -1)
        draw_text(img, name, (left - 8, y + row // 2), 0.45, align="right", valign="middle")
        label = f"{weight:.2f}" if weight >= 0.005 else "<0.01"
        draw_text(img, label, (x1 + 5, y + row // 2), 0.4, (90, 90, 90), valign="middle")
    ax.frame()
    present = {seen_in for _, _, seen_in in attended}
    draw_legend(img, [(n, c, "bar") for n, c in ATTENDED_IN if n in present], width - 60, 60)
    for k, line in enumerate(wrap_text(caption, width - 60, 0.5)[:2]):
        draw_text(img, line, (30, height - 40 + 20 * k), 0.5, (70, 70, 70))
    return write_png(path, img)


EPISODE_STEPS_SHOWN = 60  # steps listed by attention_episode_figure (a longer episode: its first 60)


def attention_episode_figure(episode: list, path, title: str, caption: str, width: int = 1200) -> Path:
    """The paper's attention example over a whole episode: one line per step, its action and its 3 most
    attended object types with their weights, each coloured by where the type was seen
    (`attention_step`'s "episode": (action, [(type, weight, ATTENDED_IN name), ...]) per step)."""
    where = dict(ATTENDED_IN)
    shown = episode[:EPISODE_STEPS_SHOWN]
    if not shown:
        raise FigureError("attention_episode_figure needs at least one step")
    line = 20
    height = 110 + line * len(shown) + 50
    img = new_canvas(title, (width, height))
    top = 90
    draw_text(img, "step", (30, top - 8), 0.45, (90, 90, 90))
    draw_text(img, "action", (90, top - 8), 0.45, (90, 90, 90))
    draw_text(img, "the 3 most attended object types", (260, top - 8), 0.45, (90, 90, 90))
    for i, (action, attended) in enumerate(shown):
        y = top + 8 + i * line
        draw_text(img, str(i + 1), (30, y), 0.45)
        draw_text(img, action, (90, y), 0.45)
        for j, (name, weight, seen_in) in enumerate(attended):
            if seen_in not in where or not math.isfinite(weight):
                raise FigureError(f"step {i + 1}: type {name!r} weight {weight!r} seen {seen_in!r}")
            x = 260 + j * 300
            cv2.rectangle(img, (x, y - 10), (x + 10, y), where[seen_in], -1)
            draw_text(img, f"{name} {weight:.2f}", (x + 16, y), 0.45)
    present = {seen_in for _, attended in shown for _, _, seen_in in attended}
    draw_legend(img, [(n, c, "bar") for n, c in ATTENDED_IN if n in present], width - 60, 60)
    more = f" (the first {EPISODE_STEPS_SHOWN} of {len(episode)} steps)" if len(episode) > len(shown) else ""
    for k, text in enumerate(wrap_text(caption + more, width - 60, 0.5)[:2]):
        draw_text(img, text, (30, height - 40 + 20 * k), 0.5, (70, 70, 70))
    return write_png(path, img)


def attention_step(
    method: str, run, kitchen: str = "FloorPlan1", seed: int = 0, row: str | None = None
) -> dict:
    """One step of a trained attention policy, as `attention_figure`'s arguments (all but the path): the
    method's plugin with the run's best-validation checkpoint, built as an evaluation builds it; the
    first fixed episode of each seen static target of `kitchen` in order, until one succeeds (else the
    last tried); in it, the step whose attention (weights >= 0.01) reaches types in the most of the
    places (view only, target only, both, neither), then the most types (the earliest of those). The
    policy must have `explain(agent, top)`, as kgnavbench's learned policies with attention do."""
    from . import evaluate
    from .env import parallel_env
    from .kitchens import object_types
    from .plugins import load_plugin
    from .tasks import load_tasks

    config = evaluate.EvalConfig(method=method, run=str(run), kitchens=(kitchen,))
    plugin = load_plugin(method)
    tasks = load_tasks(kitchen)
    spec = evaluate.policy_spec(config, evaluate.kitchen_seed(seed, kitchen), tasks.graph.views.shape[1])
    policy = plugin.make_policy(plugin.config({}), spec)
    types = {name: i for i, name in enumerate(object_types())}

    def explained(agent: str) -> list[tuple[str, float]]:
        try:
            return policy.explain(agent, top=len(types))["attention"]
        except (AttributeError, TypeError, KeyError) as e:
            raise FigureError(
                f"{method}'s policy has no explain(agent, top) -> {{'attention': [(type, weight), ...]}} "
                f"({type(e).__name__}: {first_line(e)}): no attention to draw"
            ) from e

    env = parallel_env(kitchen=kitchen, n_agents=1, targets="all", tasks=tasks, features=True)
    rows = [r for r, t in enumerate(tasks.targets) if t.seen and t.kind == "static"]
    if not rows:
        raise FigureError(f"{kitchen} has no seen static target")
    for r in rows:
        target = tasks.targets[r]
        cap = evaluate.episode_cap(evaluate.column_of(tasks.split, target.seen))
        episode = {"target": target.object_id, "start": target.starts[0], "max_steps": cap}
        observations, infos = env.reset(options={"episodes": [episode]})
        (agent,) = env.agents
        policy.reset(agent)
        steps, info = [], infos[agent]
        while env.agents:
            obs = observations[agent]
            actions = policy.act(observations, infos)
            seen = (obs["view"], obs["target"], obs["view_objects"], obs["target_objects"])
            steps.append((*seen, explained(agent), int(actions[agent])))
            observations, _, terminations, truncations, infos = env.step(actions)
            info = infos[agent]
            if terminations[agent] or truncations[agent]:
                break
        if info["success"]:
            break

    def seen_in(name: str, in_view, in_target) -> str:
        v, g = in_view[types[name]] > 0, in_target[types[name]] > 0
        return ATTENDED_IN[2 if v and g else 0 if v else 1 if g else 3][0]

    def spread(i: int) -> tuple[int, int, int]:  # places with a weight >= 0.01, types, earliest
        _, _, in_view, in_target, weights, _ = steps[i]
        places = {seen_in(n, in_view, in_target) for n, w in weights if w >= 0.01}
        return len(places), len(weights), -i

    k = max(range(len(steps)), key=spread)
    view, target_image, in_view, in_target, weights, _ = steps[k]
    if not weights:
        raise FigureError(f"{method} attended to nothing in {kitchen}'s episode: no attention to draw")
    outcome = "success" if info["success"] else "failure"
    return {
        "view": view,
        "target": target_image,
        "attended": [(name, w, seen_in(name, in_view, in_target)) for name, w in weights],
        "title": f"Attention over object types: {kitchen}, target {target.type} ({target.kind})",
        "caption": f"{row or method} ({Path(run).name}, best.pt): step {k + 1} of "
        f"{info['episode_length']} ({outcome}), the first step whose attention (weights >= 0.01) "
        f"reaches the most places, then the most types ({len(weights)}); bars: the "
        f"{min(len(weights), ATTENTION_BARS)} most attended.",
        # every step of the episode: its action and its 3 most attended types (the paper's example)
        "episode": [
            (ACTIONS[action], [(n, w, seen_in(n, v, g)) for n, w in attended[:3]])
            for _, _, v, g, attended, action in steps
        ],
    }


def attention_figures(attention: dict, out_dir) -> list[Path]:
    """attention_example.png (one step, its attention as bars) and attention_episode.png (every step's
    3 most attended types) in out_dir, from `attention_step`'s dict."""
    out_dir = Path(out_dir)
    episode = attention["episode"]
    one_step = {key: value for key, value in attention.items() if key != "episode"}
    caption = (
        attention["caption"].split(": step ")[0]
        + f": each step's 3 most attended types ({len(episode)} steps)."
    )
    return [
        attention_figure(path=out_dir / "attention_example.png", **one_step),
        attention_episode_figure(episode, out_dir / "attention_episode.png", attention["title"], caption),
    ]


# ------------------------------------------------------------------------------------------------
# The paper's figures from the table's runs

TSNE_SIZE = (1200, 900)  # more room than FIGURE_SIZE: a label per object type


def _run_dir(path, what: str) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise FigureError(f"{path}: no such {what} run directory")
    return path


def read_episodes(eval_dir) -> list[dict]:
    """Every episode of an evaluation run: the JSON lines of eval_dir/episodes/<kitchen>.jsonl."""
    eval_dir = _run_dir(eval_dir, "evaluation")
    files = sorted((eval_dir / "episodes").glob("*.jsonl"))
    if not files:
        raise FigureError(f"{eval_dir} holds no episodes/*.jsonl: not a finished evaluation run")
    episodes = []
    for path in files:
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise FigureError(f"cannot read {path}: {e}") from e
        for n, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                episode = json.loads(line)
                if not isinstance(episode, dict):
                    raise ValueError("not a JSON object")
                episodes.append(episode)
            except ValueError as e:
                raise FigureError(f"{path}, line {n}: not an episode ({e})") from e
    return episodes


def unseen_kitchen_stats(episodes: list[dict], where="episodes") -> tuple[float, float] | None:
    """(mean collisions per episode, % of episodes whose last view shows the target) over the
    episodes in unseen kitchens; None where there are none."""
    unseen = [e for e in episodes if e.get("column") == "unseen_kitchens"]
    if not unseen:
        return None
    try:
        collisions = sum(float(e["collisions"]) for e in unseen) / len(unseen)
        shown = 100.0 * sum(bool(e["last_view_shows_target"]) for e in unseen) / len(unseen)
    except (KeyError, TypeError, ValueError) as e:
        raise FigureError(
            f"{where}: an unseen-kitchens episode lacks collisions or last_view_shows_target ({e})"
        ) from e
    return collisions, shown


def _run_checkpoint(train_dir: Path, last_too: bool) -> tuple[dict, Path] | None:
    """A training run's best-validation checkpoint (with `last_too`, its last.pt where there is no
    best.pt yet: a run stopped before its first validation) and its path; None where there is none."""
    from .runs import TrainError, load_checkpoint  # lazily: recording must not cost a torch import

    path = train_dir / "best.pt"
    if last_too and not path.exists():
        path = train_dir / "last.pt"
    if not path.exists():
        return None
    try:
        return load_checkpoint(path), path
    except TrainError as e:
        raise FigureError(str(e)) from e


def _kg_checkpoint(train_dir: Path) -> tuple[dict, Path] | None:
    """The best-validation checkpoint of a training run (else its last) when its model has an
    accumulated knowledge graph, else None."""
    found = _run_checkpoint(train_dir, last_too=True)
    if found is None:
        return None
    config = found[0]["model_config"]
    if config.get("kg", "none") == "none" or config.get("kg_graph") != "accumulated":
        return None
    return found


def _attention_model(train_dir: Path) -> tuple[str, str] | None:
    """(method, attention_nodes) of a training run whose best checkpoint has a model with attention
    over its knowledge graph, else None (no best.pt yet: nothing an evaluation would test)."""
    found = _run_checkpoint(train_dir, last_too=False)
    if found is None or found[0]["model_config"].get("kg") != "attention":
        return None
    ck = found[0]
    return str(ck.get("method")), str(ck["model_config"].get("attention_nodes", "visible"))


def gcn_node_features(ck: dict, where="checkpoint") -> tuple[torch.Tensor, torch.Tensor]:
    """The third GCN layer's node features H (125, d) of a KG checkpoint over its accumulated
    co-visibility graph, and that graph's adjacency (125, 125) with the edge weights it trained on."""
    from . import models  # lazily, as above

    try:
        net = models.make_model(models.ModelConfig(**ck["model_config"]))
        net.load_state_dict(ck["model"])
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        raise FigureError(f"{where} does not fit its model ({first_line(e)})") from e
    net.eval()
    adjacency = covis.adjacency(net.cfg.kg_edges)
    with torch.no_grad():
        h = net.kg.node_features(models.normalized_adjacency(adjacency))
    return h.float(), adjacency


def tsne_figure(name: str, train_dir, out_dir, seed: int = 0, file_name: str = "tsne_gcn.png") -> Path:
    """`file_name` in out_dir: a t-SNE (seed) of the third GCN layer's node features of a run trained
    with an accumulated knowledge graph (its best-validation checkpoint, else its last), the object
    types that have a co-visibility edge (every type where fewer than 3 have), each labelled. `name`:
    the row, for the title. (`figures` draws it for a table's last KG row; call it for any KG run.)"""
    from .kitchens import object_types

    found = _kg_checkpoint(_run_dir(train_dir, "training"))
    if found is None:
        raise FigureError(f"{train_dir} trained no accumulated knowledge graph: no t-SNE of its nodes")
    ck, path = found
    h, adjacency = gcn_node_features(ck, str(path))
    keep = (adjacency.sum(1) > 0).nonzero().squeeze(1)
    if len(keep) < 3:  # no co-visibility yet: every type
        keep = torch.arange(len(h))
    types = object_types()
    return scatter_figure(
        tsne(h[keep], seed=seed),
        [types[i] for i in keep.tolist()],
        Path(out_dir) / file_name,
        f"t-SNE of the third GCN layer's node features: {name}, {len(keep)} object types "
        f"({int(ck['frames']):,} frames)",
        size=TSNE_SIZE,
    )


def figures(
    rows: list[tuple[str, str | None, str]],
    out_dir,
    seed: int = 0,
    progress=print,
    seed_runs: list[tuple[str, list[Path], bool]] = (),
) -> list[Path]:
    """The paper's figures as PNGs in out_dir from rows (Table I row name, training run dir or None,
    evaluation run dir), and `seed_curves_figure`'s from `seed_runs`:
      * collisions_unseen.png  mean collisions per episode in unseen kitchens (bars) and the rate of
                               episodes whose last view shows the target (line), per row that has
                               unseen-kitchen episodes;
      * tsne_gcn.png           a t-SNE (seed) of the third GCN layer's node features of the last row
                               with an accumulated knowledge graph, the types with an edge labelled;
      * attention_example.png  the last row trained with attention: one step of an episode in
                               FloorPlan1, its view, its target and its attention over object types
                               (`attention_step`); attention_episode.png every step of that
                               episode, its action and its 3 most attended types;
      * training_curves.png    validation SR (the training episodes' SR for a run without validation)
                               and training_reward.png mean reward per frame, vs frames, per trained row.
    A figure without data is skipped with a note to `progress`. Returns the paths written."""
    out_dir = Path(out_dir)
    # read everything first: bad input fails before any figure is (re)written
    unseen, metrics, trained = [], {}, []
    for name, train_dir, eval_dir in rows:
        stats = unseen_kitchen_stats(read_episodes(eval_dir), f"{eval_dir}")
        if stats is not None:
            unseen.append((name, *stats))
        if train_dir:
            train_dir = _run_dir(train_dir, "training")
            metrics[name] = read_metrics(train_dir / "metrics.csv")
            trained.append((name, train_dir))
    # the attention example's episode, before any figure is written: +KG+Attention in Table I, the
    # last row trained with attention over the visible nodes (else over all of them)
    attention = None
    candidates = [(name, train_dir, _attention_model(train_dir)) for name, train_dir in trained]
    candidates = [(name, d, found) for name, d, found in candidates if found is not None]
    candidates.sort(key=lambda c: c[2][1] == "visible")  # stable: the table's order within each kind
    if candidates:
        name, train_dir, (method, _) = candidates[-1]
        attention = attention_step(method, train_dir, seed=seed, row=name)
    written = []

    if unseen:
        written.append(
            bar_line_figure(
                [n for n, _, _ in unseen],
                [c for _, c, _ in unseen],
                [s for _, _, s in unseen],
                out_dir / "collisions_unseen.png",
                "Unseen kitchens: collisions per episode and last view showing the target",
                "collisions per episode",
                "last view shows target (%)",
            )
        )
    else:
        progress("figures: no row has unseen-kitchen episodes; collisions_unseen.png skipped")

    kg = None
    for name, train_dir in reversed(trained):  # the last KG row: +KG+Attention in Table I
        if _kg_checkpoint(train_dir) is not None:
            kg = (name, train_dir)
            break
    if kg is None:
        progress("figures: no row trained a knowledge graph; tsne_gcn.png skipped")
    else:
        written.append(tsne_figure(*kg, out_dir, seed))

    if attention is None:
        progress("figures: no row trained with attention; attention_example.png skipped")
    else:
        written += attention_figures(attention, out_dir)

    # validation SR where the run measured it (the checkpoint selection's number), else training SR
    success, reward, validated = {}, {}, 0
    for name, series in metrics.items():
        xs, ys = series.get("val_sr", ([], []))
        if xs:
            success[name] = (xs, ys)
            validated += 1
        elif series.get("success_rate", ([], []))[0]:
            success[f"{name} (training episodes)"] = series["success_rate"]
        if series.get("mean_reward", ([], []))[0]:
            reward[name] = series["mean_reward"]
    # a run that never succeeded draws its line on the x axis, under the others: the legend says so
    success = {(f"{n} (0 throughout)" if not any(ys) else n): (xs, ys) for n, (xs, ys) in success.items()}
    success_title = "Validation success rate during training" if validated else "Success rate during training"
    for curves, file, title, ylabel, y_include in (
        (success, "training_curves.png", success_title, "success rate (%)", (0,)),
        (reward, "training_reward.png", "Mean reward per frame during training", "mean reward per frame", ()),
    ):
        if curves:
            written.append(
                curves_figure(
                    curves, out_dir / file, title, "frames", ylabel, x_include=(0,), y_include=y_include
                )
            )
        else:
            progress(f"figures: no training run logged {ylabel}; {file} skipped")
    return written + seed_curves_figure(list(seed_runs), out_dir, progress)


# ------------------------------------------------------------------------------------------------
# every seed's training curves

SEED_CURVE_PANELS = (  # (metrics.csv column, panel title, y label, y values the axis includes, legend)
    ("val_sr", "Validation SR", "SR (%) of the validation episodes", (0,), "upper left"),
    (
        "success_rate",
        "Training-episode SR",
        "SR (%) of the training episodes that ended",
        (0, 100),
        "lower right",
    ),
)
SEED_CURVES_FILE = "training_curves_seeds"  # .png and .csv
SEED_PANEL_SIZE = (620, 560)
OWN_KITCHENS_NOTE = " (validated on its training kitchens)"  # FF A3C: its heads exist only there


def seeds_mean(curves: list[tuple[list[float], list[float]]]) -> tuple[list[float], list[float]]:
    """The mean over seeds of their k-th points (k up to the shortest seed's count), at the mean of
    their frames: every run logs at the same schedule, a few hundred frames apart (an update ends
    where its rollout does), so the k-th points are one moment of training."""
    n = min(len(xs) for xs, _ in curves)
    return (
        [sum(xs[k] for xs, _ in curves) / len(curves) for k in range(n)],
        [sum(ys[k] for _, ys in curves) / len(curves) for k in range(n)],
    )


def seed_curves_figure(rows: list[tuple[str, list[Path], bool]], out_dir, progress=print) -> list[Path]:
    """training_curves_seeds.png: validation SR and training-episode SR over frames, every seed's run
    of each row (name, its seeds' training run dirs, whether it validates in unseen kitchens) as a
    thin line and the seeds' mean as a thick one, in the row's colour; training_curves_seeds.csv: the
    points drawn, one line per run and logged row. A row without a run is left out with a note; with
    none at all nothing is written."""
    out_dir = Path(out_dir)
    rows = [(name, [_run_dir(d, "training") for d in dirs], unseen) for name, dirs, unseen in rows if dirs]
    if not rows:
        progress(f"figures: no trained row has a run; {SEED_CURVES_FILE}.png skipped")
        return []
    metrics = {str(d): read_metrics(d / "metrics.csv") for _, dirs, _ in rows for d in dirs}
    panels, table = [], []
    for column, title, ylabel, y_include, corner in SEED_CURVE_PANELS:
        series, colours, thin = {}, {}, set()
        for k, (name, dirs, unseen) in enumerate(rows):
            curves = []
            for seed, d in enumerate(dirs):
                xs, ys = metrics[str(d)].get(column, ([], []))
                if xs:
                    curves.append(([x / 1e6 for x in xs], list(ys)))
                    table += [(name, seed, d.name, x, column, y) for x, y in zip(xs, ys)]
            if not curves:
                continue
            note = OWN_KITCHENS_NOTE if column == "val_sr" and not unseen else ""
            label = f"{name}, {len(curves)} seed{'s' if len(curves) > 1 else ''}{note}"
            if len(curves) > 1:
                for seed, curve in enumerate(curves):
                    series[f"{label} #{seed}"] = curve
                    colours[f"{label} #{seed}"] = k
                    thin.add(f"{label} #{seed}")
            series[label], colours[label] = seeds_mean(curves) if len(curves) > 1 else curves[0], k
        if series:
            panels.append(
                curves_image(
                    series,
                    title,
                    "frames (millions)",
                    ylabel,
                    SEED_PANEL_SIZE,
                    x_include=(0,),
                    y_include=y_include,
                    colours=colours,
                    thin=frozenset(thin),
                    legend_corner=corner,
                )
            )
        else:
            progress(f"figures: no run logged {column}; its panel of {SEED_CURVES_FILE}.png is left out")
    if not panels:
        progress(f"figures: no run logged a success rate; {SEED_CURVES_FILE}.png skipped")
        return []
    csv_path = out_dir / f"{SEED_CURVES_FILE}.csv"
    text = io.StringIO()  # csv quotes a row name holding a comma or a quote
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(["row", "seed", "run", "frames", "column", "value"])
    writer.writerows(
        (name, seed, run, frames, column, f"{value:g}") for name, seed, run, frames, column, value in table
    )
    atomic_write(csv_path, text.getvalue())
    return [write_png(out_dir / f"{SEED_CURVES_FILE}.png", np.concatenate(panels, axis=1)), csv_path]


def trained_seed_runs(preset, rows, trained: Path, device: str, progress=print):
    """(row name, its seeds' finished runs in `trained`, whether it validates in unseen kitchens) for
    each row of `rows` that trains; a seed whose run is not there is left out with a note."""
    from . import jobs  # lazily: the table stage imports the trainer

    found = []
    for row in rows:
        if not jobs.trains(row):
            continue
        dirs = []
        for seed in range(preset.seeds_of(row.name)):
            try:
                dirs.append(
                    jobs.find_trained(
                        preset, row, seed, jobs.row_options(preset, row), trained, device, progress
                    )
                )
            except KgnavbenchError as e:
                progress(f"figures: {first_line(e).split('; the closest')[0]}: drawn without it")
        found.append((row.name, dirs, row.unseen_kitchens))
    return found


def figures_of_table(
    preset: str = "quick",
    runs_dir="runs",
    out_dir="docs/figures",
    spec_path=None,
    progress=print,
    trained=None,
    device: str = "cpu",
    rows_named: tuple[str, ...] = (),
    curves_only: bool = False,
) -> list[Path]:
    """The figures of a Table I preset's runs (run_table: finished runs are only reloaded, missing
    ones are trained and evaluated first; with `trained`, a folder such as zoo/, the trained runs come
    from there and none is trained), from each row's first seed, and every seed's training curves;
    `rows_named`: those rows only. `curves_only`: only the seeds' training curves, from the runs
    `trained` holds (a seed it lacks is left out with a note), nothing trained or evaluated."""
    from . import jobs, table, table_spec  # lazily: the table stage imports the trainer

    spec = table_spec.load_spec(spec_path) if spec_path else table_spec.load_spec()
    if curves_only:
        if trained is None:
            raise FigureError(
                "the training curves alone are drawn from the runs of a --trained folder (zoo/)"
            )
        chosen = spec.preset(preset)
        rows = jobs.only_rows(spec, chosen, rows_named)
        found = trained_seed_runs(chosen, rows, Path(trained), device, progress)
        return seed_curves_figure(found, out_dir, progress)
    if trained is None and device == "cpu" and not rows_named:
        result = table.run_table(spec, preset, runs_dir, progress=progress)
    else:  # a run trained on CUDA is another run (its device is in its config): the table's, as asked
        sources = jobs.Sources(None if trained is None else Path(trained))
        result = table.run_table(
            spec, preset, runs_dir, progress=progress, device=device, sources=sources, rows_named=rows_named
        )
    rows = [(r.row.name, r.train_runs[0] or None, r.eval_runs[0]) for r in result.rows]
    seed_runs = [
        (r.row.name, [Path(d) for d in r.train_runs if d], r.row.unseen_kitchens) for r in result.rows
    ]
    return figures(rows, out_dir, progress=progress, seed_runs=seed_runs)
