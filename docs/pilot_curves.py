"""The paper-protocol pilot's curves: validation SR and training-episode SR over the frames of each run
named, side by side, up to --frames. Reads each run's metrics.csv (a run folder of runs/train/ or zoo/)
through the package's own reader and draws with its plotting functions.

    python docs/pilot_curves.py --frames 10000000 --out docs/figures/paper_protocol_pilot.png \\
        "LSTM A3C=zoo/lstm_a3c-60ac5e8459" "+IL=zoo/lstm_a3c-e6f9f30b6c"
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from kgnavbench.plots import curves_image, write_png
from kgnavbench.record import read_metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", metavar="LABEL=RUN_DIR")
    parser.add_argument("--frames", type=int, default=10_000_000, help="the curves up to these frames")
    parser.add_argument("--out", type=Path, default=Path("docs/figures/paper_protocol_pilot.png"))
    parser.add_argument("--title", default="seed 0")
    args = parser.parse_args()
    validation, training = {}, {}
    for item in args.runs:
        label, _, run_dir = item.partition("=")
        metrics = read_metrics(Path(run_dir) / "metrics.csv")
        for curves, column in ((validation, "val_sr"), (training, "success_rate")):
            xs, ys = metrics.get(column, ([], []))
            # (a validation row lands a few hundred frames past its multiple of 2.5M)
            kept = [(x / 1e6, y) for x, y in zip(xs, ys) if x <= args.frames * 1.001]
            curves[label] = ([x for x, _ in kept], [y for _, y in kept])
    panels = [
        curves_image(
            validation,
            f"Validation SR, {args.title}",
            "frames (millions)",
            "SR (%), 745 validation episodes",
            (500, 520),
            x_include=(0,),
            y_include=(0,),
        ),
        curves_image(
            training,
            f"Training-episode SR, {args.title}",
            "frames (millions)",
            "SR (%) of the episodes that ended",
            (500, 520),
            x_include=(0,),
            y_include=(0, 100),
        ),
    ]
    print(write_png(args.out, np.concatenate(panels, axis=1)))


if __name__ == "__main__":
    main()
