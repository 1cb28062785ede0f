"""The `kgnavbench walk` command: the agent stepped through a kitchen's pymunk world, printing (or
saving) what it sees at every step. A helper of kgnavbench/cli.py, without a stage number: it looks at
the world and render stages directly, as a person checking a kitchen would.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import sys
from pathlib import Path

from .errors import KgnavbenchError
from .kitchens import Kitchen, load_kitchen
from .world import ACTIONS, Pose, World, parse_action, parse_pose

MIN_SIZE, MAX_SIZE = 16, 1024
MAP_MIN_SIZE = 300
MAX_RANDOM_ACTIONS = 100_000  # a walk prints a line per step: more is a typo, not a walk


class WalkError(KgnavbenchError, ValueError):
    """Bad walk input (actions, start pose, output folder): one `kgnavbench: error: ...` line, exit 2."""


def parse_actions(text: str, rng: random.Random) -> list[str]:
    """Comma-separated action names and/or `random:N` items (N actions drawn with `rng`).

    Every item is checked before anything runs, so a typo fails before the first step."""
    actions: list[str] = []
    items = [item.strip() for item in text.split(",")]
    if not text.strip() or any(not item for item in items):
        raise WalkError(
            f"bad --actions {text!r}: expected comma-separated actions like MoveAhead,RotateLeft or random:N"
        )
    for item in items:
        if item.startswith("random:"):
            count = item[len("random:") :]
            if not re.fullmatch(r"[0-9]+", count) or int(count) > MAX_RANDOM_ACTIONS:
                limit = f"0 <= N <= {MAX_RANDOM_ACTIONS:,}"
                raise WalkError(f"bad --actions item {item!r}: random:N needs a whole number {limit}")
            actions.extend(rng.choice(ACTIONS) for _ in range(int(count)))
        else:
            actions.append(parse_action(item))
    return actions


def parse_start(text: str, kitchen: Kitchen) -> Pose:
    """`world.parse_pose`, plus the checks it lacks: finite numbers, whole-degree heading and pitch."""
    try:
        parts = [float(v) for v in text.split(",")]
    except ValueError:
        parts = []
    if parts and not all(math.isfinite(v) for v in parts):
        raise WalkError(f"bad pose {text!r}: x, z, heading and pitch must be finite numbers")
    if any(v != int(v) for v in parts[2:]):
        raise WalkError(f"bad pose {text!r}: heading and pitch must be whole degrees")
    return parse_pose(text, kitchen)


def pose_dict(pose: Pose) -> dict:
    return {"x": pose.x, "z": pose.z, "heading": pose.heading, "pitch": pose.pitch}


def walk(args: argparse.Namespace) -> int:
    """`kgnavbench walk`: check every input, then step and print (or write views and a map)."""
    from . import render  # OpenCV and numpy start here; `kgnavbench kitchens` does without them

    # --- check every input before the first step
    kitchen = load_kitchen(args.kitchen)
    actions = parse_actions(args.actions, random.Random(args.seed))
    world = World(kitchen, seed=args.placement_seed)
    if args.start is not None:
        world.teleport(parse_start(args.start, kitchen))
    out: Path | None = args.out
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise WalkError(f"cannot create output folder {str(out)!r}: {e.strerror or e}") from None
        if not os.access(out, os.W_OK):
            raise WalkError(f"output folder {str(out)!r} is not writable")

    open_width = max([len("open receptacle")] + [len(o.id) for o in world.objects if o.openable])

    def report(step: int, action: str | None, success: bool) -> None:
        visible = [world.objects[i].id for i in render.visible_objects(world)]
        if args.json:
            record = {
                "step": step,
                "action": action,
                "success": success,
                "pose": pose_dict(world.pose),
                "open_receptacle": world.open_receptacle,
                "visible": visible,
            }
            print(json.dumps(record), flush=True)
        else:
            print(
                f"{step:4d}  {action or '(start)':<11}  {'ok' if success else 'FAILED':<6}  "
                f"{str(world.pose):<22}  {world.open_receptacle or '-':<{open_width}}  "
                f"{' '.join(visible) or '-'}",
                flush=True,
            )
        if out is not None:
            render.save_rgb(out / f"view_{step:03d}.png", render.render_view(world, world.pose, args.size))

    if not args.json:
        print(
            f"{'step':>4}  {'action':<11}  {'result':<6}  {'pose x,z,heading,pitch':<22}  "
            f"{'open receptacle':<{open_width}}  visible"
        )
    path = [world.pose]
    failed = 0
    report(0, None, True)
    for step, action in enumerate(actions, start=1):
        result = render.act(world, action)
        failed += not result.success
        path.append(world.pose)
        report(step, action, result.success)

    where = "no files written (use --out DIR to save views and a map)"
    if out is not None:
        size = max(args.size, MAP_MIN_SIZE)
        render.save_rgb(out / "map.png", render.top_down_map(world, size=size, poses=[world.pose], path=path))
        where = f"{len(actions) + 1} views and map.png written to {out}"
    summary = f"{kitchen.name}: {len(actions)} steps, {failed} failed; {where}"
    # with --json, stdout stays one JSON object per line
    print(summary, file=sys.stderr if args.json else sys.stdout)
    return 0
