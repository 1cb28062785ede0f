"""Contact sheet of rendered views: four headings in several kitchens, and FloorPlan1's Fridge closed
and open (the Egg inside). Writes docs/contact_sheet.png. Run: make docs
"""

from pathlib import Path

import cv2
import numpy as np

from kgnavbench.render import act, render_views, save_rgb, top_down_map
from kgnavbench.world import HEADINGS, Pose, World

KITCHENS = ("FloorPlan1", "FloorPlan7", "FloorPlan16", "FloorPlan24", "FloorPlan28")
TILE = 240
FRIDGE_POSE = Pose((-4, 4), 270, 30)  # FloorPlan1: x=-1.00, z=1.00, facing the Fridge


def label(image: np.ndarray, text: str) -> np.ndarray:
    image = image.copy()
    cv2.rectangle(image, (0, 0), (image.shape[1], 18), (0, 0, 0), -1)
    cv2.putText(image, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def central_cell(world: World) -> tuple[int, int]:
    cells = world.kitchen.reachable
    cx = sum(c[0] for c in cells) / len(cells)
    cz = sum(c[1] for c in cells) / len(cells)
    return min(cells, key=lambda c: (c[0] - cx) ** 2 + (c[1] - cz) ** 2)


def main() -> None:
    rows = []
    for name in KITCHENS:
        world = World(name)
        cell = central_cell(world)
        poses = [Pose(cell, h, 0) for h in HEADINGS]
        views, _ = render_views(world, poses, TILE)
        tiles = [label(v, f"{name} {p}") for v, p in zip(views, poses)]
        tiles.append(label(top_down_map(world, TILE, poses=poses[:1]), f"{name} map"))
        rows.append(np.concatenate(tiles, 1))
    world = World("FloorPlan1")
    world.teleport(FRIDGE_POSE)
    closed = render_views(world, [FRIDGE_POSE], TILE)[0][0]
    result = act(world, "OpenObject")
    opened = render_views(world, [FRIDGE_POSE], TILE)[0][0]
    up = render_views(world, [Pose(FRIDGE_POSE.cell, 270, -30)], TILE)[0][0]
    fridge_map = top_down_map(world, TILE, poses=[FRIDGE_POSE])
    rows.append(
        np.concatenate(
            [
                label(closed, "FloorPlan1 Fridge closed"),
                label(opened, f"OpenObject: {'ok' if result.success else 'FAILED'} (Egg inside)"),
                label(up, "open, LookUp (pitch -30)"),
                label(render_views(world, [Pose(FRIDGE_POSE.cell, 270, 60)], TILE)[0][0], "open, pitch 60"),
                label(fridge_map, "map: door swung open"),
            ],
            1,
        )
    )
    out = Path(__file__).parent / "contact_sheet.png"
    save_rgb(out, np.concatenate(rows, 0))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
