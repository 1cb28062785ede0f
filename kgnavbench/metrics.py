"""Stage 20 — metrics: one episode's record and Table I's metrics over many.

An evaluation's episodes are EpisodeResult records (kitchen, target, column, kind, success, path
lengths, collisions, what the last view showed). `summarize` groups them per Table I cell (column and
kind, and their totals) into Metrics: SR and SPL (Anderson et al.: S * L / max(P, L)) in percent, the
same on episodes whose shortest path is at least LONG_PATH, collisions per episode, how often the last
view showed the target, and the mean episode length. `format_summary` writes them as a table,
`summary_as_json` as `eval --json` prints them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

COLUMNS = ("seen_seen", "seen_unseen", "unseen_kitchens")
COLUMN_TITLES = {
    "seen_seen": "seen kitchens / seen targets",
    "seen_unseen": "seen kitchens / unseen targets",
    "unseen_kitchens": "unseen kitchens",
    "validation": "validation kitchens",
}
KINDS = ("static", "actionable")
LONG_PATH = 5  # a long episode's shortest path, in actions (the SR L>=5 and SPL L>=5 columns)


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
    # whether the episode ended by the agent's Stop (else by its cap); None in results files written
    # before it was recorded. With Stop ending the episode, it lets one evaluation be scored under the
    # other success rule (`evaluate.rescored`)
    stopped: bool | None = None


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
    for column in {r.column for r in results}:  # a kind with no episodes in a column: an empty cell
        for kind in KINDS:
            groups.setdefault((column, kind), [])
    order = [*COLUMNS, "validation", "all"]
    keys = sorted(groups, key=lambda k: (order.index(k[0]), (*KINDS, "all").index(k[1])))
    return {k: metrics(groups[k]) for k in keys}


def format_summary(summary: dict[tuple[str, str], Metrics], title: str) -> str:
    """The Table I layout for one method: a row per column and kind."""
    head = [
        "column",
        "kind",
        "episodes",
        "SR (%)",
        "SPL (%)",
        "SR L>=5 (%)",
        "SPL L>=5 (%)",
        "collisions/episode",
        "last view (%)",
        "length (steps)",
    ]

    def cell(value: float, digits: int = 2) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}f}"  # no episodes: no number, not 0

    rows = []
    for (column, kind), m in summary.items():
        rows.append(
            [
                COLUMN_TITLES.get(column, "all columns"),
                kind,
                f"{m.episodes}",
                cell(m.sr),
                cell(m.spl),
                cell(m.sr_long),
                cell(m.spl_long),
                cell(m.collisions),
                cell(m.last_view_shows_target),
                cell(m.episode_length, 1),
            ]
        )
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    lines = [title, "| " + " | ".join(h.ljust(w) for h, w in zip(head, widths)) + " |"]
    lines.append("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        cells = [c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary_as_json(summary: dict[tuple[str, str], Metrics]) -> dict:
    """{"column/kind": metrics}, an empty cell's NaN as null (JSON has no NaN)."""
    return {
        f"{c}/{k}": {f: (None if isinstance(v, float) and math.isnan(v) else v) for f, v in asdict(m).items()}
        for (c, k), m in summary.items()
    }
