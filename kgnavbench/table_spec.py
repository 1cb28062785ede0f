"""Stage 25 — table_spec: the table spec (`tables/table1.toml`), read and checked.

The spec names the protocol (success rule, Stop, episode caps, checkpoint selection), the presets
(frames per row, episodes per target, seeds, kitchens, training options), the rows (a plugin and its
options each, with the paper's numbers for the paper's rows) and the comparisons the paper draws
between rows. `load_spec` / `parse_spec` turn it into a `TableSpec`; anything wrong with it is a
TableError naming the file and the field. `CELLS` names Table I's five cells.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .env import SUCCESS_RULES
from .errors import KgnavbenchError
from .evaluate import SEEN_CAP, UNSEEN_CAP
from .kitchens import KITCHEN_NAMES
from .plugins import available
from .tasks import EPISODES_PER_TARGET, load_task_file

SPEC_FILE = Path(__file__).resolve().parent.parent / "tables" / "table1.toml"
# which checkpoint of a run a table evaluates: "best_val_sr", Table I's rule (the run's best.pt: the
# highest validation SR, ties to the later); "last", the run's final weights (last.pt)
CHECKPOINT_RULES = ("best_val_sr", "last")
PRESET_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,39}")
# Table I's five cells (column, kind), in the paper's order. The sixth pair of evaluate's columns and
# kinds, actionable targets in seen kitchens that are unseen, never has an episode: every actionable
# target of a training kitchen is a seen one.
CELLS = (
    ("seen_seen", "static"),
    ("seen_unseen", "static"),
    ("unseen_kitchens", "static"),
    ("seen_seen", "actionable"),
    ("unseen_kitchens", "actionable"),
)
CELL_KEYS = tuple(f"{column}/{kind}" for column, kind in CELLS)  # "column/kind", as the spec's `paper`
CELL_TITLES = {
    "seen_seen/static": "static seen/seen",
    "seen_unseen/static": "static seen/unseen",
    "unseen_kitchens/static": "static unseen kitchens",
    "seen_seen/actionable": "actionable seen/seen",
    "unseen_kitchens/actionable": "actionable unseen kitchens",
}
METRICS = ("SPL", "SR")  # in the paper's order; a `paper` pair is [SPL, SR]
# the largest margin of "no difference beyond" a spec may state: a wider one would call differences of
# the size the paper reports for its components (3-9 SR points) no difference
MAX_MARGIN = 3.0
PERCENT = 100.0  # episode values are kept in percent: every mean and interval is then in percent


class TableError(KgnavbenchError, ValueError):
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
    # points: an interval of a difference within [-margin, margin] reads "no difference beyond MARGIN"
    margin: float


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
    rows: tuple[str, ...] = ()  # the rows this preset runs, by name; empty: every row of the spec
    checkpoint: str = ""  # the checkpoint rule of its evaluations (CHECKPOINT_RULES); empty: the protocol's
    # the training kitchens whose unseen targets are evaluated (the seen kitchens / unseen targets
    # column); the other training kitchens get their seen targets only. Empty: every target.
    unseen_target_kitchens: tuple[str, ...] = ()
    # the success rule its cells are scored under; empty: the protocol's. "visible" on a protocol of
    # "destination" with Stop ending the episode scores the same evaluations (`evaluate.scored_visible`)
    score_rule: str = ""
    # a row's own number of seeds where it differs from `seeds` (row name -> seeds 0..n-1): more seeds
    # where they decide the paper's comparisons (docs/table1.md), without training every row again
    row_seeds: dict[str, int] = field(default_factory=dict)

    def seeds_of(self, row: str) -> int:
        """How many seeds (0..n-1) the row named `row` trains and evaluates under this preset."""
        return self.row_seeds.get(row, self.seeds)

    def seeds_text(self) -> str:
        """ "3 seeds" or "3 seeds (+KG: 6)": what a caption says of the preset's seeds."""
        text = f"{self.seeds} seed{'' if self.seeds == 1 else 's'}"
        if self.row_seeds:
            text += " (" + "; ".join(f"{name}: {n}" for name, n in self.row_seeds.items()) + ")"
        return text

    @property
    def threads(self) -> int:
        """torch's threads in every job (the `threads` training option; 0: not set, torch's own)."""
        return int(self.options.get("threads", "0"))


@dataclass(frozen=True)
class Row:
    name: str
    method: str
    options: dict[str, str]
    unseen_kitchens: bool = True  # False: the method has no unseen-kitchens row (FF A3C)
    paper: dict[str, tuple[float, float]] = field(default_factory=dict)  # "column/kind" -> (SPL, SR)


@dataclass(frozen=True)
class Comparison:
    """A comparison the paper draws: `other` (a row with a component added) should beat `base`."""

    base: str
    other: str


@dataclass(frozen=True)
class TableSpec:
    path: Path
    protocol: Protocol
    presets: dict[str, Preset]
    rows: tuple[Row, ...]
    comparisons: tuple[Comparison, ...] = ()

    def preset(self, name: str) -> Preset:
        """The preset called `name`; a TableError naming the spec's presets otherwise."""
        if name not in self.presets:
            raise TableError(f"unknown preset {name!r}; {self.path} has {', '.join(self.presets)}")
        return self.presets[name]


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
    """The spec from TOML text; every problem is a TableError naming the file and the field.

    :param text: the spec's TOML
    :param path: the file it was read from, named in every error
    """
    path = Path(path)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise TableError(f"{path}: not valid TOML ({e})") from e
    except RecursionError as e:  # arrays or tables nested thousands deep
        raise TableError(f"{path}: nested too deeply to be a table spec") from e
    _unknown(str(path), raw, {"protocol", "presets", "rows", "comparisons"})
    protocol = _protocol(f"{path}: protocol", _field(str(path), raw, "protocol", dict))
    presets = {}
    for name, table in _field(str(path), raw, "presets", dict).items():
        presets[name] = _preset(path, name, table, protocol)
    if not presets:
        raise TableError(f"{path}: presets has none")
    methods = set(available())
    listed = _field(str(path), raw, "rows", list)
    rows = [_row(f"{path}: rows[{i}]", t, methods) for i, t in enumerate(listed)]
    if not rows:
        raise TableError(f"{path}: rows has none")
    names = [r.name for r in rows]
    if len(set(names)) != len(names):
        raise TableError(f"{path}: rows: a row name is used twice")
    for preset in presets.values():
        _check_preset_rows(path, preset, names)
    comparisons = _comparisons(path, _field(str(path), raw, "comparisons", list, [], required=False), names)
    return TableSpec(path, protocol, presets, tuple(rows), comparisons)


def _protocol(where: str, p: dict) -> Protocol:
    """The spec's [protocol]: the evaluation's rule, Stop, caps, checkpoint rule and verdict margin."""
    _unknown(where, p, {"success_rule", "stop_ends", "seen_cap", "unseen_cap", "checkpoint", "margin"})
    protocol = Protocol(
        success_rule=_field(where, p, "success_rule", str),
        stop_ends=_field(where, p, "stop_ends", bool),
        seen_cap=_field(where, p, "seen_cap", int),
        unseen_cap=_field(where, p, "unseen_cap", int),
        checkpoint=_field(where, p, "checkpoint", str),
        # optional: a spec that states none reads "no difference" only where the interval is exactly 0
        margin=float(_field(where, p, "margin", (int, float), 0, required=False)),
    )
    if not 0 <= protocol.margin <= MAX_MARGIN:
        raise TableError(f"{where}.margin = {protocol.margin:g} must be 0..{MAX_MARGIN:g} points")
    if protocol.success_rule not in SUCCESS_RULES:
        raise TableError(f"{where}.success_rule = {protocol.success_rule!r}: choose one of {SUCCESS_RULES}")
    if protocol.success_rule == "arrival" and protocol.stop_ends:
        raise TableError(f"{where}: success_rule 'arrival' makes Stop a no-op: stop_ends must be false")
    if (protocol.seen_cap, protocol.unseen_cap) != (SEEN_CAP, UNSEEN_CAP):
        raise TableError(
            f"{where}: seen_cap/unseen_cap = {protocol.seen_cap}/{protocol.unseen_cap}, but the evaluation "
            f"protocol's caps are {SEEN_CAP}/{UNSEEN_CAP}"
        )
    if protocol.checkpoint not in CHECKPOINT_RULES:
        raise TableError(f"{where}.checkpoint = {protocol.checkpoint!r}: choose one of {CHECKPOINT_RULES}")
    return protocol


def _preset(path: Path, name: str, t, protocol: Protocol) -> Preset:
    """One [presets.NAME] table, checked on its own (its rows against the spec's: `_check_preset_rows`)."""
    where = f"{path}: presets.{name}"
    if not PRESET_NAME.fullmatch(name):  # it names files (tables/table1-NAME.md) and claims
        raise TableError(
            f"{path}: preset name {name!r} must be letters, digits, '-' and '_' (at most 40), "
            "starting with a letter or digit"
        )
    if not isinstance(t, dict):
        raise TableError(f"{where} must be a table")
    _unknown(
        where,
        t,
        {
            "description",
            "frames",
            "episodes",
            "seeds",
            "train_kitchens",
            "eval_kitchens",
            "set",
            "rows",
            "checkpoint",
            "unseen_target_kitchens",
            "score_rule",
            "row_seeds",
        },  # fmt: skip
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
        eval_kitchens=_kitchens(f"{where}.eval_kitchens", _field(where, t, "eval_kitchens", list, [], False)),
        options=_options(f"{where}.set", _field(where, t, "set", dict, {}, required=False)),
        rows=tuple(_field(where, t, "rows", list, [], required=False)),
        checkpoint=_field(where, t, "checkpoint", str, "", required=False),
        score_rule=_field(where, t, "score_rule", str, "", required=False),
        row_seeds=_row_seeds(f"{where}.row_seeds", _field(where, t, "row_seeds", dict, {}, False)),
        # in the kitchens' order: the same kitchens listed otherwise are the same evaluations
        unseen_target_kitchens=tuple(
            sorted(
                _kitchens(
                    f"{where}.unseen_target_kitchens",
                    _field(where, t, "unseen_target_kitchens", list, [], False),
                ),
                key=KITCHEN_NAMES.index,
            )
        ),
    )
    _check_preset(where, preset, protocol)
    return preset


def _check_preset(where: str, preset: Preset, protocol: Protocol) -> None:
    """A preset's values against each other and the protocol: its unseen-target kitchens trained and
    evaluated, its checkpoint and score rules known, frames, episodes and seeds in range."""
    train_split = load_task_file()["splits"]["train"] if preset.unseen_target_kitchens else []
    training = set(train_split) & set(preset.eval_kitchens or train_split)
    elsewhere = [k for k in preset.unseen_target_kitchens if k not in training]
    if elsewhere:
        raise TableError(
            f"{where}.unseen_target_kitchens: {', '.join(elsewhere)} "
            f"{'is' if len(elsewhere) == 1 else 'are'} not a training kitchen that the preset evaluates"
        )
    if preset.checkpoint and preset.checkpoint not in CHECKPOINT_RULES:
        raise TableError(f"{where}.checkpoint = {preset.checkpoint!r}: choose one of {CHECKPOINT_RULES}")
    scorable = (protocol.success_rule, "visible") == (
        "destination",
        preset.score_rule,
    ) and protocol.stop_ends
    if preset.score_rule not in ("", protocol.success_rule) and not scorable:
        raise TableError(
            f"{where}.score_rule = {preset.score_rule!r}: the only other rule a table scores its "
            "evaluations under is 'visible', on a protocol of 'destination' where Stop ends episodes"
        )
    if preset.frames < 1:
        raise TableError(f"{where}.frames = {preset.frames} must be at least 1")
    if not 1 <= preset.episodes <= EPISODES_PER_TARGET:
        raise TableError(f"{where}.episodes = {preset.episodes} must be 1..{EPISODES_PER_TARGET}")
    if not 1 <= preset.seeds <= 100:
        raise TableError(f"{where}.seeds = {preset.seeds} must be 1..100")


def _row(where: str, t, methods: set[str]) -> Row:
    """One [[rows]] table: its name, plugin, options and the paper's numbers."""
    if not isinstance(t, dict):
        raise TableError(f"{where} must be a table")
    _unknown(where, t, {"name", "method", "options", "unseen_kitchens", "paper"})
    method = _field(where, t, "method", str)
    if method not in methods:
        raise TableError(
            f"{where}.method = {method!r} is not a plugin (available: {', '.join(sorted(methods))})"
        )
    paper = {}
    for cell, pair in _field(where, t, "paper", dict, {}, required=False).items():
        ok = cell in CELL_KEYS and isinstance(pair, list) and len(pair) == 2
        if not ok or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pair):
            raise TableError(
                f"{where}.paper.{cell!r} = {pair!r} must be CELL = [SPL, SR], a CELL one of Table I's "
                f"{', '.join(CELL_KEYS)}"
            )
        paper[cell] = (float(pair[0]), float(pair[1]))
    return Row(
        name=_field(where, t, "name", str),
        method=method,
        options=_options(f"{where}.options", _field(where, t, "options", dict, {}, required=False)),
        unseen_kitchens=_field(where, t, "unseen_kitchens", bool, True, required=False),
        paper=paper,
    )


def _check_preset_rows(path: Path, preset: Preset, names: list[str]) -> None:
    """A preset's `rows` and `row_seeds` name rows of the spec, each once, and extra seeds are extra."""
    runs = preset.rows or names
    fewer = [(n, k) for n, k in preset.row_seeds.items() if k <= preset.seeds]
    if fewer:  # a row's extra seeds follow every job of the first `seeds`: it cannot have fewer
        raise TableError(
            f"{path}: presets.{preset.name}.row_seeds: {fewer[0][0]!r} = {fewer[0][1]} is not more than "
            f"the preset's seeds = {preset.seeds}; row_seeds is for rows that need more"
        )
    elsewhere = [n for n in preset.row_seeds if n not in runs]
    if elsewhere:
        raise TableError(
            f"{path}: presets.{preset.name}.row_seeds: {elsewhere[0]!r} is not a row of the preset "
            f"(its rows: {'; '.join(runs)})"
        )
    unknown = [n for n in preset.rows if n not in names]
    if unknown or len(set(preset.rows)) != len(preset.rows):
        raise TableError(
            f"{path}: presets.{preset.name}.rows = {list(preset.rows)!r}: "
            + (f"{unknown[0]!r} is not a row name" if unknown else "a row is named twice")
        )


def _row_seeds(where: str, table: dict) -> dict[str, int]:
    """`row_seeds = { "ROW" = N }`: a row's own number of seeds, 1..100 (row names are checked later)."""
    out = {}
    for name, n in table.items():
        if not isinstance(n, int) or isinstance(n, bool) or not 1 <= n <= 100:
            raise TableError(f"{where}.{name!r} = {n!r} must be a number of seeds, 1..100")
        out[name] = n
    return out


def _comparisons(path: Path, tables: list, row_names: list[str]) -> tuple[Comparison, ...]:
    """`[[comparisons]]`: each {base, other}, two different rows of the spec, no pair twice."""
    out: list[Comparison] = []
    for i, t in enumerate(tables):
        where = f"{path}: comparisons[{i}]"
        if not isinstance(t, dict):
            raise TableError(f"{where} must be a table with base and other")
        _unknown(where, t, {"base", "other"})
        comparison = Comparison(base=_field(where, t, "base", str), other=_field(where, t, "other", str))
        for key in ("base", "other"):
            name = getattr(comparison, key)
            if name not in row_names:
                raise TableError(f"{where}.{key} = {name!r} is not a row name (rows: {', '.join(row_names)})")
        if comparison.base == comparison.other:
            raise TableError(f"{where}: base and other are the same row {comparison.base!r}")
        if comparison in out:
            raise TableError(f"{where}: {comparison.other!r} against {comparison.base!r} is there twice")
        out.append(comparison)
    return tuple(out)


MAX_SPEC_BYTES = 1_000_000  # the committed spec is about 20 kB; more is not a table spec


def load_spec(path: Path | str = SPEC_FILE) -> TableSpec:
    """The spec file (UTF-8 TOML, at most MAX_SPEC_BYTES); every problem is one TableError."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise TableError(f"table spec {path}: {e.strerror or e}") from e
    if len(data) > MAX_SPEC_BYTES:
        raise TableError(f"table spec {path}: {len(data):,} bytes, more than a spec's {MAX_SPEC_BYTES:,}")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise TableError(f"table spec {path}: not UTF-8 text (byte {e.start})") from e
    return parse_spec(text, path)
