"""Stage 10 — table: the paper's Table I from a table spec (`tables/table1.toml`).

The spec names the protocol (success rule, Stop, episode caps, checkpoint selection), the presets
(frames per row, episodes per target, seeds, kitchens, training options) and the nine rows (a plugin
and its options each, with the paper's numbers where our sources have them). `run_table` goes row by
row: train unless a finished run with the same config exists (an unfinished one resumes), take the
checkpoint with the best validation SR, evaluate it on the fixed episodes (per-episode JSON lines in
the eval run), then write the table as markdown, CSV and LaTeX. Everything it runs is a resumable run
directory, so a killed `make table` continues where it stopped.

Cells are SPL / SR in percent per Table I column (seen kitchens / seen targets, seen kitchens / unseen
targets, unseen kitchens) and target kind (static, actionable); "–" where there are no episodes (no
actionable target of a training kitchen is unseen) or the method has no row (FF A3C in unseen kitchens).
With several seeds a cell is mean ± standard deviation over seeds.
"""

from __future__ import annotations

import csv
import io
import statistics
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .env import SUCCESS_RULES
from .evaluate import (
    COLUMN_TITLES,
    COLUMNS,
    KINDS,
    SEEN_CAP,
    UNSEEN_CAP,
    EvalConfig,
    EvalRun,
    evaluate,
    git_revision,
)
from .kitchens import KITCHEN_NAMES, atomic_write
from .plugins import PluginError, available, load_plugin
from .tasks import EPISODES_PER_TARGET, load_task_file
from .train import train_method

SPEC_FILE = Path(__file__).resolve().parent.parent / "tables" / "table1.toml"
CHECKPOINT_RULES = ("best_val_sr",)
CELLS = [(c, k) for c in COLUMNS for k in KINDS]  # the twelve SPL/SR pairs of a row, in order


class TableError(ValueError):
    """A bad table spec (the message names the file and the field) or a failed table run."""


# ------------------------------------------------------------------------------------------------
# The spec


@dataclass(frozen=True)
class Protocol:
    success_rule: str
    stop_ends: bool
    seen_cap: int
    unseen_cap: int
    checkpoint: str


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    frames: int  # training frames per row and seed
    episodes: int  # fixed episodes per target, of 100
    seeds: int
    train_kitchens: tuple[str, ...]  # empty: all training kitchens
    eval_kitchens: tuple[str, ...]  # empty: Table I's kitchens (train + test)
    options: dict[str, str]  # training options for every learned row (`set`)


@dataclass(frozen=True)
class Row:
    name: str
    method: str
    options: dict[str, str]
    unseen_kitchens: bool = True  # False: the method has no unseen-kitchens row (FF A3C)
    paper: dict[str, tuple[float, float]] = field(default_factory=dict)  # "column/kind" -> (SPL, SR)
    paper_note: str = ""


@dataclass(frozen=True)
class TableSpec:
    path: Path
    protocol: Protocol
    presets: dict[str, Preset]
    rows: tuple[Row, ...]


def _field(where: str, table: dict, key: str, kind, default=None, required=True):
    """table[key] checked against kind; a TableError naming `where.key` otherwise."""
    if key not in table:
        if required:
            raise TableError(f"{where}.{key} is missing")
        return default
    value = table[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        names = " or ".join(k.__name__ for k in kinds)
        raise TableError(f"{where}.{key} = {value!r} must be {names}")
    return value


def _unknown(where: str, table: dict, known: set[str]) -> None:
    extra = sorted(set(table) - known)
    if extra:
        raise TableError(
            f"{where} has unknown field(s) {', '.join(extra)} (known: {', '.join(sorted(known))})"
        )


def _options(where: str, value: dict) -> dict[str, str]:
    """Option tables as typed on the command line: every value a string, a number or a bool."""
    out = {}
    for k, v in value.items():
        if isinstance(v, bool):
            out[k] = "true" if v else "false"
        elif isinstance(v, (str, int, float)):
            out[k] = str(v)
        else:
            raise TableError(f"{where}.{k} = {v!r} must be a string, number or bool")
    return out


def _kitchens(where: str, names: list) -> tuple[str, ...]:
    for k in names:
        if k not in KITCHEN_NAMES:
            raise TableError(f"{where}: unknown kitchen {k!r}")
    if len(set(names)) != len(names):
        raise TableError(f"{where}: a kitchen is named twice")
    return tuple(names)


def parse_spec(text: str, path: Path | str = "<spec>") -> TableSpec:
    """The spec from TOML text; every problem is a TableError naming the file and the field."""
    path = Path(path)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TableError(f"{path}: not valid TOML ({e})") from e
    _unknown(str(path), raw, {"protocol", "presets", "rows"})
    where = f"{path}: protocol"
    p = _field(str(path), raw, "protocol", dict)
    _unknown(where, p, {"success_rule", "stop_ends", "seen_cap", "unseen_cap", "checkpoint"})
    protocol = Protocol(
        success_rule=_field(where, p, "success_rule", str),
        stop_ends=_field(where, p, "stop_ends", bool),
        seen_cap=_field(where, p, "seen_cap", int),
        unseen_cap=_field(where, p, "unseen_cap", int),
        checkpoint=_field(where, p, "checkpoint", str),
    )
    if protocol.success_rule not in SUCCESS_RULES:
        raise TableError(f"{where}.success_rule = {protocol.success_rule!r}: choose one of {SUCCESS_RULES}")
    if (protocol.seen_cap, protocol.unseen_cap) != (SEEN_CAP, UNSEEN_CAP):
        raise TableError(
            f"{where}: seen_cap/unseen_cap = {protocol.seen_cap}/{protocol.unseen_cap}, but the evaluation "
            f"protocol's caps are {SEEN_CAP}/{UNSEEN_CAP}"
        )
    if protocol.checkpoint not in CHECKPOINT_RULES:
        raise TableError(f"{where}.checkpoint = {protocol.checkpoint!r}: choose one of {CHECKPOINT_RULES}")

    presets = {}
    for name, t in _field(str(path), raw, "presets", dict).items():
        where = f"{path}: presets.{name}"
        if not isinstance(t, dict):
            raise TableError(f"{where} must be a table")
        _unknown(
            where, t, {"description", "frames", "episodes", "seeds", "train_kitchens", "eval_kitchens", "set"}
        )
        preset = Preset(
            name=name,
            description=_field(where, t, "description", str, "", required=False),
            frames=_field(where, t, "frames", int),
            episodes=_field(where, t, "episodes", int),
            seeds=_field(where, t, "seeds", int, 1, required=False),
            train_kitchens=_kitchens(
                f"{where}.train_kitchens", _field(where, t, "train_kitchens", list, [], False)
            ),
            eval_kitchens=_kitchens(
                f"{where}.eval_kitchens", _field(where, t, "eval_kitchens", list, [], False)
            ),
            options=_options(f"{where}.set", _field(where, t, "set", dict, {}, required=False)),
        )
        if preset.frames < 1:
            raise TableError(f"{where}.frames = {preset.frames} must be at least 1")
        if not 1 <= preset.episodes <= EPISODES_PER_TARGET:
            raise TableError(f"{where}.episodes = {preset.episodes} must be 1..{EPISODES_PER_TARGET}")
        if not 1 <= preset.seeds <= 100:
            raise TableError(f"{where}.seeds = {preset.seeds} must be 1..100")
        presets[name] = preset
    if not presets:
        raise TableError(f"{path}: presets has none")

    rows = []
    methods = set(available())
    for i, t in enumerate(_field(str(path), raw, "rows", list)):
        where = f"{path}: rows[{i}]"
        if not isinstance(t, dict):
            raise TableError(f"{where} must be a table")
        _unknown(where, t, {"name", "method", "options", "unseen_kitchens", "paper", "paper_note"})
        method = _field(where, t, "method", str)
        if method not in methods:
            raise TableError(
                f"{where}.method = {method!r} is not a plugin (available: {', '.join(sorted(methods))})"
            )
        paper = {}
        for cell, pair in _field(where, t, "paper", dict, {}, required=False).items():
            column, _, kind = cell.partition("/")
            ok = column in COLUMNS and kind in KINDS and isinstance(pair, list) and len(pair) == 2
            if not ok or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair):
                raise TableError(
                    f"{where}.paper.{cell!r} must be COLUMN/KIND = [SPL, SR] (columns {COLUMNS})"
                )
            paper[cell] = (float(pair[0]), float(pair[1]))
        rows.append(
            Row(
                name=_field(where, t, "name", str),
                method=method,
                options=_options(f"{where}.options", _field(where, t, "options", dict, {}, required=False)),
                unseen_kitchens=_field(where, t, "unseen_kitchens", bool, True, required=False),
                paper=paper,
                paper_note=_field(where, t, "paper_note", str, "", required=False),
            )
        )
    if not rows:
        raise TableError(f"{path}: rows has none")
    names = [r.name for r in rows]
    if len(set(names)) != len(names):
        raise TableError(f"{path}: rows: a row name is used twice")
    return TableSpec(path, protocol, presets, tuple(rows))


def load_spec(path: Path | str = SPEC_FILE) -> TableSpec:
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise TableError(f"table spec {path}: {e.strerror or e}") from e
    return parse_spec(text, path)


# ------------------------------------------------------------------------------------------------
# Running the rows


@dataclass
class RowResult:
    row: Row
    seeds: list[dict[str, tuple[float, float] | None]]  # per seed: "column/kind" -> (SPL, SR) or None
    train_runs: list[str]
    eval_runs: list[str]
    seconds: float


@dataclass
class TableResult:
    spec: TableSpec
    preset: Preset
    rows: list[RowResult]
    seconds: float
    git_revision: str


def _cells(run: EvalRun) -> dict[str, tuple[float, float] | None]:
    out = {}
    for column, kind in CELLS:
        m = run.summary.get((column, kind))
        out[f"{column}/{kind}"] = None if m is None or m.episodes == 0 else (m.spl, m.sr)
    return out


def eval_kitchens(preset: Preset, row: Row) -> tuple[str, ...]:
    """The preset's evaluation kitchens (all of Table I's by default), without unseen kitchens for a
    method that has no row there."""
    splits = load_task_file()["splits"]
    kitchens = preset.eval_kitchens or tuple(
        sorted(splits["train"] + splits["test"], key=KITCHEN_NAMES.index)
    )
    if not row.unseen_kitchens:
        kitchens = tuple(k for k in kitchens if k in splits["train"])
    return kitchens


def run_row(spec: TableSpec, preset: Preset, row: Row, seed: int, runs_dir: Path, progress) -> tuple:
    """Train (or find, or resume) one row's run for one seed, then evaluate its best checkpoint."""
    trains = _trains(row)
    options = dict(row.options)
    run_dir = None
    if trains:
        options = {**preset.options, **row.options}
        run_dir = train_method(
            row.method, options, preset.frames, seed, preset.train_kitchens, runs_dir, progress=progress
        )
    config = EvalConfig(
        method=row.method,
        options=tuple(sorted(options.items())),
        success_rule=spec.protocol.success_rule,
        stop_ends=spec.protocol.stop_ends,
        split="table",
        kitchens=eval_kitchens(preset, row),
        episodes_per_target=preset.episodes,
        seed=seed,
        run=str(run_dir) if run_dir else "",
    )
    return run_dir, evaluate(config, runs_dir, progress=progress)


def _trains(row: Row) -> bool:
    try:
        return callable(getattr(load_plugin(row.method).module, "train", None))
    except PluginError as e:
        raise TableError(f"row {row.name!r}: {e}") from e


def time_left(done: list[tuple[bool, float]], todo: list[bool]) -> float | None:
    """Seconds left: per kind of row (trained or not), the mean time of the rows of that kind done so
    far times the rows of that kind to come; None while a kind to come has none done (a random walk's
    seconds say nothing about a training run's minutes)."""
    left = 0.0
    for kind in (True, False):
        coming = sum(1 for k in todo if k == kind)
        times = [t for k, t in done if k == kind]
        if coming and not times:
            return None
        left += coming * (sum(times) / len(times) if times else 0.0)
    return left


def run_table(
    spec: TableSpec, preset_name: str, runs_dir: Path | str = "runs", progress=print
) -> TableResult:
    """Every row, one after another, with progress and an ETA; resumable (see the module docstring)."""
    if preset_name not in spec.presets:
        raise TableError(f"unknown preset {preset_name!r}; {spec.path} has {', '.join(spec.presets)}")
    preset = spec.presets[preset_name]
    runs_dir = Path(runs_dir)
    start = time.perf_counter()
    results = []
    jobs = [(row, seed) for row in spec.rows for seed in range(preset.seeds)]
    per_row: dict[str, RowResult] = {}
    kinds = [_trains(row) for row, _ in jobs]
    done: list[tuple[bool, float]] = []
    for n, (row, seed) in enumerate(jobs):
        left = time_left(done, kinds[n:])
        eta = f", about {left / 60:.0f} min left" if left is not None else ""
        progress(f"== [{n + 1}/{len(jobs)}] {row.name} (seed {seed}){eta}")
        t0, started = time.perf_counter(), time.time()
        try:
            run_dir, run = run_row(spec, preset, row, seed, runs_dir, progress)
        except PluginError as e:
            raise TableError(f"row {row.name!r}: {e}") from e
        # a row found done on disk took seconds, not what a row of its kind takes: no ETA sample
        reused = (
            run_dir is not None and (run_dir / "finished.json").stat().st_mtime < started
            if kinds[n]
            else len(run.resumed) == len(run.config.kitchen_list())
        )
        result = per_row.setdefault(row.name, RowResult(row, [], [], [], 0.0))
        result.seeds.append(_cells(run))
        result.train_runs.append(str(run_dir) if run_dir else "")
        result.eval_runs.append(str(run.directory))
        result.seconds += time.perf_counter() - t0
        if not reused:
            done.append((kinds[n], time.perf_counter() - t0))
    results = [per_row[row.name] for row in spec.rows]
    return TableResult(spec, preset, results, time.perf_counter() - start, git_revision())


# ------------------------------------------------------------------------------------------------
# Writing the table


def combine(values: list[tuple[float, float] | None]) -> tuple[str, str]:
    """(SPL, SR) text of one cell over seeds: '12.34', or '12.34 ± 1.20' with several seeds; '–' for none."""
    present = [v for v in values if v is not None]
    if not present:
        return "–", "–"
    out = []
    for i in (0, 1):
        xs = [v[i] for v in present]
        mean = sum(xs) / len(xs)
        out.append(f"{mean:.2f}" if len(xs) == 1 else f"{mean:.2f} ± {statistics.stdev(xs):.2f}")
    return out[0], out[1]


def _header() -> list[str]:
    short = {"seen_seen": "seen/seen", "seen_unseen": "seen/unseen", "unseen_kitchens": "unseen kitchens"}
    head = ["method"]
    for column, kind in CELLS:
        head += [f"{short[column]} {kind} SPL", f"{short[column]} {kind} SR"]
    return head


def table_rows(result: TableResult) -> list[list[str]]:
    """One line per method (ours), and one per method with the paper's numbers where the spec has any."""
    lines = []
    for r in result.rows:
        cells = [r.row.name]
        for column, kind in CELLS:
            cells += combine([s[f"{column}/{kind}"] for s in r.seeds])
        lines.append(cells)
        if r.row.paper:
            paper = [f"{r.row.name} (paper)"]
            for column, kind in CELLS:
                pair = r.row.paper.get(f"{column}/{kind}")
                paper += [f"{pair[0]:.2f}", f"{pair[1]:.2f}"] if pair else ["–", "–"]
            lines.append(paper)
    return lines


def caption(result: TableResult) -> str:
    p, pr = result.preset, result.spec.protocol
    rule = "Stop at the destination" if pr.success_rule == "destination" else "Stop with the target visible"
    stop = "Stop ends the episode" if pr.stop_ends else "a wrong Stop is a no-op"
    notes = "; ".join(
        f"{r.row.name}: the paper prints {r.row.paper_note}" for r in result.rows if r.row.paper_note
    )
    return (
        f"Table I regenerated by kgnavbench, preset {p.name!r} ({p.description}): {p.frames:,} training "
        f"frames per learned row, {p.episodes} of the 100 fixed episodes per target, {p.seeds} seed(s)"
        f"{' (mean ± std)' if p.seeds > 1 else ''}; success = {rule}, {stop}; caps {pr.seen_cap} "
        f"(seen kitchens, seen targets) / {pr.unseen_cap}; the checkpoint with the best validation SR. "
        f"Cells: SPL / SR in %; '–': no episodes in the cell. Git {result.git_revision}, "
        f"wall time {result.seconds / 60:.1f} min." + (f" {notes}." if notes else "")
    )


def to_markdown(result: TableResult) -> str:
    head = _header()
    lines = [f"**{caption(result)}**", ""]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|---" + "|---:" * (len(head) - 1) + "|")
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(result)]
    return "\n".join(lines) + "\n"


def to_csv(result: TableResult) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["# " + caption(result)])
    writer.writerow(_header())
    writer.writerows(table_rows(result))
    return out.getvalue()


def _tex_escape(text: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#")):
        text = text.replace(a, b)
    return text.replace("±", r"$\pm$").replace("–", "--")


def to_latex(result: TableResult) -> str:
    groups = " & ".join(rf"\multicolumn{{4}}{{c}}{{{COLUMN_TITLES[c]}}}" for c in COLUMNS)
    kinds = " & ".join(r"\multicolumn{2}{c}{" + k + "}" for _ in COLUMNS for k in KINDS)
    lines = [
        r"\begin{table*}",
        r"\centering",
        r"\caption{" + _tex_escape(caption(result)) + "}",
        r"\begin{tabular}{l" + "rr" * len(CELLS) + "}",
        r"\hline",
        rf" & {groups} \\",
        rf" & {kinds} \\",
        " & " + " & ".join(["SPL & SR"] * len(CELLS)) + r" \\",
        r"\hline",
    ]
    lines += [" & ".join(_tex_escape(c) for c in row) + r" \\" for row in table_rows(result)]
    lines += [r"\hline", r"\end{tabular}", r"\end{table*}"]
    return "\n".join(lines) + "\n"


def write_table(result: TableResult, out_dir: Path | str) -> list[Path]:
    """tables/table1.{md,csv,tex} for the quick preset, table1-<preset>.* for the others."""
    out_dir = Path(out_dir)
    stem = "table1" if result.preset.name == "quick" else f"table1-{result.preset.name}"
    paths = []
    for suffix, text in ((".md", to_markdown(result)), (".csv", to_csv(result)), (".tex", to_latex(result))):
        path = out_dir / f"{stem}{suffix}"
        try:
            atomic_write(path, text)
        except OSError as e:
            raise TableError(f"cannot write {path}: {e.strerror or e}") from e
        paths.append(path)
    return paths
