"""Whether two output folders (a table's --out and --runs, before and after a refactor) hold the same
files with the same contents, apart from what differs between any two runs of the same code: the
folders' own paths, the checkout's path, the git revision, and wall times.

    python benchmarks/same_outputs.py BEFORE AFTER [--checkouts /work/before /work/main] [--by-content]

Prints one line per file that differs (with the first differing line) and a count; exits 1 if any.
--by-content compares the files whatever folders hold them: a run directory is named by a hash of the
training code, so a refactor of that code renames every run and evaluation folder while their files
stay the same; each file name's normalised contents (run-folder names blanked) must then be the same
multiset before and after.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

# what differs between two runs of the same code
VOLATILE = [
    (re.compile(r'"?git_revision"?: ?"[^"]*"'), "git_revision: REV"),
    (re.compile(r"Git [0-9a-f]{40}(-dirty)?"), "Git REV"),
    (re.compile(r"wall time [0-9.]+ (min|s)"), "wall time T"),
    (re.compile(r'"seconds": [0-9.e+-]+'), '"seconds": T'),
]
METRICS_TIMES = ("seconds", "frames_per_s")  # metrics.csv columns that are wall times


def normalised(path: Path, root: Path, checkout: str) -> str:
    text = path.read_text(errors="replace").replace(str(root), "ROOT").replace(checkout, "CHECKOUT")
    for pattern, replacement in VOLATILE:
        text = pattern.sub(replacement, text)
    if path.name == "metrics.csv":
        lines = text.splitlines()
        head = lines[0].split(",") if lines else []
        drop = {i for i, name in enumerate(head) if name in METRICS_TIMES}
        text = "\n".join(
            ",".join(c for i, c in enumerate(line.split(",")) if i not in drop) for line in lines
        )
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--checkouts", nargs=2, default=("", ""), metavar=("BEFORE", "AFTER"))
    parser.add_argument("--by-content", action="store_true", help="match files by name and content")
    args = parser.parse_args()
    if args.by_content:
        return by_content(args)
    files = {
        p.relative_to(root): root
        for root in (args.before, args.after)
        for p in root.rglob("*")
        if p.is_file() and p.suffix not in (".log",)
    }
    differ = 0
    for rel in sorted(files):
        a, b = args.before / rel, args.after / rel
        if not a.exists() or not b.exists():
            print(f"only in {'after' if not a.exists() else 'before'}: {rel}")
            differ += 1
            continue
        if a.read_bytes() == b.read_bytes():
            continue
        if a.suffix in (".pt", ".png", ".gz", ".rrd"):
            print(f"differs (binary): {rel}")
            differ += 1
            continue
        ta = normalised(a, args.before, args.checkouts[0] or "\0")
        tb = normalised(b, args.after, args.checkouts[1] or "\0")
        if ta != tb:
            first = next(
                (f"{x!r} / {y!r}" for x, y in zip(ta.splitlines(), tb.splitlines()) if x != y),
                "lengths differ",
            )
            print(f"differs: {rel}: {first[:300]}")
            differ += 1
    print(f"{len(files)} files, {differ} differ beyond paths, git revision and wall times")
    return 1 if differ else 0


RUN_NAME = re.compile(r"(?<=[a-z_])-(?:[a-z]+-stop-(?:ends|noop)-[a-z]+-)?[0-9a-f]{8,10}\b")


def by_content(args) -> int:
    """Each file name's normalised contents, as a multiset, before and after."""
    import collections

    sides = []
    for root, checkout in ((args.before, args.checkouts[0]), (args.after, args.checkouts[1])):
        seen = collections.Counter()
        for p in root.rglob("*"):
            if p.is_file() and p.suffix != ".log":
                if p.suffix in (".pt", ".png", ".gz", ".rrd", ".npy", ".npz"):
                    content = p.read_bytes().hex()
                else:
                    content = RUN_NAME.sub("-RUN", normalised(p, root, checkout or "\0"))
                seen[(p.name if not RUN_NAME.search(p.name) else RUN_NAME.sub("-RUN", p.name), content)] += 1
        sides.append(seen)
    only_before, only_after = sides[0] - sides[1], sides[1] - sides[0]
    for (name, _), n in sorted(only_before.items()):
        print(f"differs: {name} ({n} before without its match after)")
    before, after, unmatched = sum(sides[0].values()), sum(sides[1].values()), sum(only_before.values())
    print(f"{before} files before, {after} after; {unmatched} without an equal file after")
    return 1 if only_before or only_after else 0


if __name__ == "__main__":
    sys.exit(main())
