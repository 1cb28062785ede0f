"""The command line's value types and input checks (kgnavbench/cli.py's), each failing with a
UsageError: one `kgnavbench: error: ...` line and exit status 2, before any work starts. A helper
without a stage number."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from .errors import KgnavbenchError
from .kitchens import KITCHEN_NAMES, check_name
from .plugins import MAX_SEED
from .tasks import EPISODES_PER_TARGET


class UsageError(KgnavbenchError):
    """Bad command-line input: reported as one `kgnavbench: error: ...` line, exit status 2."""


def kitchen_list(text: str | None) -> list[str]:
    """`--kitchens A,B`: every name known, none twice, none empty; no option: all 30."""
    if text is None:
        return list(KITCHEN_NAMES)
    names = [k.strip() for k in text.split(",")]
    if not text.strip() or any(not k for k in names):
        raise UsageError(
            f"bad --kitchens {text!r}: expected comma-separated kitchens like FloorPlan1,FloorPlan5"
        )
    twice = sorted({k for k in names if names.count(k) > 1})
    if twice:
        raise UsageError(f"bad --kitchens {text!r}: {', '.join(twice)} named twice")
    return [check_name(k) for k in names]


def json_safe(value):
    """NaN and infinities (a cell without episodes) as JSON's null: `--json` is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def integer_in(text: str, low: int, high: int) -> int:
    """An integer option's value, low..high (argparse reports the error with the option's name)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not low <= n <= high:
        raise argparse.ArgumentTypeError(f"{n} is not in {low}..{high}")
    return n


def positive(text: str) -> int:
    return integer_in(text, 1, 256)


def seconds(text: str) -> float:
    """A time limit in seconds: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} is no time limit (a number of seconds above 0)")
    return value


def seed(text: str) -> int:
    return integer_in(text, 0, MAX_SEED)


def writable_folder(path: Path, what: str) -> None:
    """Make the folder (and its parents) or say in one line why it cannot be: before any work starts,
    not after minutes of training."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{what} {str(path)!r}: cannot write there ({e.strerror or e})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {str(path)!r}: cannot write there (no permission)")


def writable_file(path: Path, what: str) -> None:
    """The file's folder must exist and be writable, and the file itself, if it exists."""
    folder = path.parent
    if path.is_dir():
        raise UsageError(f"{what} {str(path)!r} is a folder, not a file")
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {str(path)!r}: its folder {str(folder)!r} is missing or not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise UsageError(f"{what} {str(path)!r} is not writable")


def device_name(name: str) -> str:
    """--device resolved to what a run records: "cpu" or "cuda" (a UsageError where it cannot be)."""
    from .device import DeviceError, name_of, resolve

    try:
        return name_of(resolve(name))
    except DeviceError as e:
        raise UsageError(str(e)) from e


def frames(text: str) -> int:
    """A frame count: an integer, underscores or a k/M suffix allowed (2M, 500k, 2_000_000)."""
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1:].lower(), 1)
    try:
        n = round(float((text[:-1] if scale > 1 else text).replace("_", "")) * scale)
    except (ValueError, OverflowError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a frame count (e.g. 2000000, 2M, 500k)") from None
    if not 1 <= n <= 10**12:
        raise argparse.ArgumentTypeError(f"{text} is not in 1..10^12 frames")
    return n


def episodes(text: str) -> int:
    return integer_in(text, 1, EPISODES_PER_TARGET)
