"""A picture of the rerun viewer on a recording, taken headless: `rerun FILE.rrd --headless
--screenshot-to PNG` (rerun 0.41; no display or browser needed, it draws with whatever Vulkan or GL
device there is, Mesa's software one here). The viewer shoots as soon as it has drawn, sometimes
before the recording has loaded (a dark, empty window): such a picture is taken again, up to
`--attempts` times, and a bigger recording loads slower (record fewer steps: `eval --record-steps`).

    python docs/screenshot.py runs/kg_attention_episodes.rrd docs/figures/rerun_viewer.png
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

from kgnavbench.record import check_recording, rerun_command

# mean grey level (0-255) of a picture with the views, map and plots drawn; the empty viewer is ~16
DRAWN = 30.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--size", default="1600x1000", help="window size in points (the PNG's size)")
    parser.add_argument("--attempts", type=int, default=5)
    args = parser.parse_args()
    recording = check_recording(args.recording)
    width, height = (int(v) for v in args.size.split("x"))
    env = {**os.environ, "RUST_LOG": "error"}  # no notification pop-ups over the plots
    with tempfile.TemporaryDirectory() as tmp:
        shot = Path(tmp) / "viewer.png"
        for attempt in range(1, args.attempts + 1):
            command = [*rerun_command(), str(recording), "--headless", "--screenshot-to", str(shot)]
            command += ["--window-size", args.size, "--hide-welcome-screen"]
            subprocess.run(command, env=env, check=True, timeout=300, stderr=subprocess.DEVNULL)
            image = cv2.imread(str(shot))
            grey = float(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).mean())
            print(f"attempt {attempt}: mean grey {grey:.1f} ({'drawn' if grey > DRAWN else 'still loading'})")
            if grey > DRAWN:
                # the viewer renders at twice the points on this display scale: back to the window size
                image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
                args.out.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(args.out), image)
                print(f"wrote {args.out}")
                return 0
    print(f"the viewer never finished loading {recording} in {args.attempts} attempts", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
