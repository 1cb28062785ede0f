"""The documentation: README.md stays a guide read in one sitting, every repository path that
README.md and docs/*.md name exists, every commit they name is in the history, they name nothing a
reader of a clone cannot follow, and the numbers they repeat are computed from zoo/ and tables/."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README_MAX_LINES = 400

# a token that starts with one of these, or is one of the names below, is a path into the repository
PREFIXES = (
    "kgnavbench/",
    "baselines/",
    "benchmarks/",
    "tables/",
    "tests/",
    "docs/",
    "zoo/",
    "examples/",
    ".ci/",
)
TOP_LEVEL_FILES = ("Makefile", "pyproject.toml", "README.md")
GYMNASIUM_ID = re.compile(r"kgnavbench/[\w.-]+-v\d+")  # `kgnavbench/FloorPlan1-v0` is an env id, not a path

FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def prose(path: Path) -> str:
    """The document without its fenced code blocks (commands there may create files)."""
    return FENCE.sub("", path.read_text(encoding="utf-8"))


def is_placeholder(path: str) -> bool:
    return any(mark in path for mark in ("*", "<", "{", "..."))


def named_paths(path: Path) -> list[str]:
    """Repository paths named in `code spans` (each whitespace-separated token), relative to the root."""
    found = []
    for span in CODE_SPAN.finditer(prose(path)):
        for token in span.group(2).split():
            token = token.strip("'\"()[],;:").split("#")[0]
            if is_placeholder(token) or GYMNASIUM_ID.fullmatch(token):
                continue
            if token.startswith(PREFIXES) or token in TOP_LEVEL_FILES:
                found.append(token)
    return found


def linked_paths(path: Path) -> list[Path]:
    """Local targets of markdown links and images, resolved against the document's folder; links that
    leave the repository (`../shared/...`) and web addresses are not checked here."""
    found = []
    for link in LINK.finditer(prose(path)):
        target = link.group(1).split("#")[0]
        if not target or re.match(r"[a-z][a-z0-9+.-]*:", target, re.I) or is_placeholder(target):
            continue  # an anchor in the same document, a URL or mailto:, a placeholder
        resolved = (path.parent / target).resolve()
        if resolved.is_relative_to(ROOT):
            found.append(resolved)
    return found


def test_the_readme_is_read_in_one_sitting():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; at most {README_MAX_LINES}"
    # its Table I section: the one table a reader needs, the verdicts in a few lines, docs/table1.md for more
    start = lines.index("## Table I, and how to read it")
    end = next(n for n in range(start + 1, len(lines)) if lines[n].startswith("## "))
    section = "\n".join(lines[start:end]).rstrip().splitlines()
    assert len(section) <= 45, f"README's Table I section has {len(section)} lines; at most 45"


def test_every_path_the_docs_name_exists():
    missing = []
    for doc in documents():
        where = doc.relative_to(ROOT)
        missing += [f"{where}: `{p}`" for p in named_paths(doc) if not (ROOT / p.rstrip("/")).exists()]
        missing += [f"{where}: link {p.relative_to(ROOT)}" for p in linked_paths(doc) if not p.exists()]
    assert not missing, "paths named in the docs that do not exist:\n" + "\n".join(missing)


def test_each_stage_imports_only_the_stages_before_it():
    """docs/stages.md's data flow is the package's: every stage it names is a file of kgnavbench/, and
    no stage imports a stage after it (helpers such as files.py or intervals.py are not stages)."""
    import ast

    block = (ROOT / "docs" / "stages.md").read_text().split("```")[1]
    flow = [word for word in re.split(r"[\s>-]+", block) if word]
    place = {stage: n for n, stage in enumerate(flow)}
    assert len(place) == len(flow) > 20, flow
    later = []
    for stage in flow:
        path = ROOT / "kgnavbench" / f"{stage}.py"
        assert path.is_file(), f"docs/stages.md names the stage {stage}, but {path.name} does not exist"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                names = [node.module.split(".")[0]] if node.module else [a.name for a in node.names]
                later += [
                    f"{stage} imports {n} (line {node.lineno})"
                    for n in names
                    if place.get(n, -1) >= place[stage]
                ]
    assert not later, "stages that import a stage after them:\n" + "\n".join(later)


def _zoo_runs_by_preset() -> tuple[dict[str, int], dict[str, float]]:
    """From zoo/ itself: each preset's runs (the first preset zoo/README.md's listing names for each
    run, as `kgnavbench ship` writes it) and their training time in core-hours (finished.json)."""
    listing = (ROOT / "zoo" / "README.md").read_text().split("<!-- the listing below")[1].split("<!-- end")[0]
    runs, hours = {}, {}
    for line in listing.splitlines():
        match = re.match(r"\| `([^`]+)` \| [^|]+ \| ([^|,]+)[^|]* \|", line)
        if match:
            run, preset = match.group(1), match.group(2).strip()
            finished = json.loads((ROOT / "zoo" / run / "finished.json").read_text())
            runs[preset] = runs.get(preset, 0) + 1
            hours[preset] = hours.get(preset, 0.0) + finished["seconds"] / 3600
    return runs, hours


def test_the_readmes_zoo_counts_and_core_hours_are_the_zoos():
    """The README's count of zoo/'s runs per preset and the paper preset's core-hours are computed here
    from zoo/ (never written into this test): a shipped run that the prose does not count fails."""
    text = " ".join((ROOT / "README.md").read_text().split())
    runs, hours = _zoo_runs_by_preset()
    assert f"`zoo/` holds {runs['paper']} runs of 40M frames of the paper preset" in text
    assert f"and {runs.get('paper-protocol', 0)} of the paper-protocol preset" in text
    assert f"{hours['paper']:.1f} core-hours for its {runs['paper']} runs in `zoo/`" in text


def test_the_training_codes_files_are_listed_as_runs_names_them():
    """docs/reproducibility.md lists the files whose syntax trees name a run: runs.TRAINING_CODE's."""
    from kgnavbench.runs import TRAINING_CODE

    text = " ".join((ROOT / "docs" / "reproducibility.md").read_text().split())
    listed = ", ".join(f"`{name}`" for name in TRAINING_CODE)
    assert f"the training code ({listed}: `runs.TRAINING_CODE`" in text


def _cannot_tell(preset: str) -> tuple[int, int]:
    """(SR cells, SR cells whose verdict is cannot tell) of a committed ablation CSV."""
    import csv

    lines = (ROOT / "tables" / f"table1-{preset}-ablation.csv").read_text().splitlines()[1:]
    sr = [r for r in csv.DictReader(lines) if r["metric"] == "SR"]
    return len(sr), sum(r["verdict"] == "cannot tell" for r in sr)


def test_the_readmes_cannot_tell_counts_are_the_committed_tables():
    """The README's counts of SR cells that cannot tell, computed from the committed ablation CSVs."""
    text = " ".join((ROOT / "README.md").read_text().split())
    cells, last = _cannot_tell("paper-last")
    rule = _cannot_tell("paper")[1]
    assert f"Final weights: {last} of {cells} SR cells *cannot tell* (rule: {rule})" in text


def referencing_documents() -> list[Path]:
    """The pages a reader follows references from: README.md, zoo/README.md and docs/*.md."""
    return [*documents(), ROOT / "zoo" / "README.md"]


# a commit as the docs name it: 7-40 hex digits with a digit and a letter, standing alone (a run's or
# an evaluation's name, `method-0123456789`, and a 64-digit checksum are not commits)
COMMIT = re.compile(r"(?<![\w./-])(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w-])")


def test_every_commit_the_docs_name_is_in_the_history():
    """A commit a page names resolves with `git rev-parse` (a reader can `git show` it)."""
    import subprocess

    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: no history to resolve commits in")
    named = {}
    for doc in referencing_documents():
        for commit in COMMIT.findall(doc.read_text(encoding="utf-8")):
            named.setdefault(commit, []).append(str(doc.relative_to(ROOT)))
    assert len(named) > 5, named  # the docs do name the pinned revisions
    unknown = [
        f"{commit} (in {', '.join(sorted(set(where)))})"
        for commit, where in sorted(named.items())
        if subprocess.run(
            ["git", "rev-parse", "--quiet", "--verify", f"{commit}^{{commit}}"],
            cwd=ROOT,
            capture_output=True,
        ).returncode
    ]
    assert not unknown, "commits the docs name that are not in the history:\n" + "\n".join(unknown)


# what a reader of a clone cannot follow: a path on the machine that wrote a page (the cache's
# ~/.cache/kgnavbench is every user's own and stays), an issue number, a session, an unnamed machine
UNFOLLOWABLE = {
    "a path outside the repository": (
        re.compile(r"(?<![\w.])(?:/tmp\b|/root\b|/home/|~/(?!\.cache/kgnavbench))"),
        "name the command or the repository file instead",
    ),
    "a numbered issue": (
        re.compile(r"\b[Ii]ssues? #?\d+|(?<![\w&])#\d+\b"),
        "say what was asked for; a clone has no issue tracker",
    ),
    "a session": (
        re.compile(r"\b[Ss]essions?\b"),
        "give the date, the commit or the machine",
    ),
    "an unnamed machine": (
        re.compile(r"\b(?:development machines?|this machine(?! kind)|the machine this)\b", re.I),
        "name it by what it is: docs/reproducibility.md#the-machines-behind-the-figures",
    ),
}


@pytest.mark.parametrize("kind", sorted(UNFOLLOWABLE))
def test_the_docs_name_nothing_a_reader_cannot_follow(kind):
    pattern, instead = UNFOLLOWABLE[kind]
    found = [
        f"{doc.relative_to(ROOT)}:{n}: {line.strip()[:120]}"
        for doc in referencing_documents()
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1)
        if pattern.search(line)
    ]
    assert not found, f"{kind} in the docs ({instead}):\n" + "\n".join(found)


def test_every_pages_zoo_counts_and_core_hours_are_the_zoos():
    """Wherever a manual page (not the journal, whose entries keep their day's numbers) counts the
    paper preset's runs in zoo/ or their core-hours, the number is the zoo's own."""
    runs, hours = _zoo_runs_by_preset()
    counts = re.compile(
        r"(\d+) runs (?:of 40M frames )?(?:of the paper preset|in `zoo/`)"
        r"|zoo's (\d+) runs of the paper preset"
    )
    core_hours = re.compile(r"(\d+\.\d) core-hours (?:of training )?for (?:its |the )?(\d+) runs")
    found, wrong = 0, []
    for doc in referencing_documents():
        if doc.name == "history.md":
            continue
        text = " ".join(doc.read_text(encoding="utf-8").split())
        for match in counts.finditer(text):
            found += 1
            if int(match.group(1) or match.group(2)) != runs["paper"]:
                wrong.append(f"{doc.relative_to(ROOT)}: '{match.group(0)}' (zoo/ holds {runs['paper']})")
        for match in core_hours.finditer(text):
            found += 1
            if (match.group(1), int(match.group(2))) != (f"{hours['paper']:.1f}", runs["paper"]):
                zoo = f"zoo/: {hours['paper']:.1f} for {runs['paper']}"
                wrong.append(f"{doc.relative_to(ROOT)}: '{match.group(0)}' ({zoo})")
    assert found >= 4, found  # the README, speed.md, status.md and table1.md state them
    assert not wrong, "counts of the zoo's runs that are not the zoo's:\n" + "\n".join(wrong)


def test_the_trainer_reads_top_to_bottom():
    """No function of the trainer's and the table's own files (train.py, rollout.py, table.py) is over
    60 lines, none in the package over 100, and the rollout is a loop, not a generator."""
    import ast

    long = []
    for path in sorted((ROOT / "kgnavbench").glob("*.py")):
        limit = 60 if path.name in ("train.py", "rollout.py", "table.py") else 100
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit:
                    long.append(f"kgnavbench/{path.name}: {node.name} has {lines} lines (at most {limit})")
                if path.name == "rollout.py":
                    assert not any(isinstance(n, (ast.Yield, ast.YieldFrom)) for n in ast.walk(node)), (
                        node.name
                    )
    assert not long, "functions to split by job:\n" + "\n".join(long)
