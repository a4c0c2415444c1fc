"""How well the fine relief is read: the slope above the network's 128 px band, read from a
1024 px photo, against the truth's, on the relief reader's validation set (the detail benchmark's
calibration relief: 12 procedural materials from seed 500001000, one family after another,
photographed as ``evaluate`` photographs them).

    .venv/bin/python benchmarks/relief_reader.py [--reader runs/relief_reader/best.safetensors]

Rows: the shipped network's normal unit (``capturing.detail.fine_relief``, unweighted), the same
scaled by 0.6 (near its least error: an estimate of correlation c is best at c^2 of the truth's
energy), the unit as one octave, as a reader started from it reads before training
(``relief_reader.from_normal_unit``), and each ``--reader`` (``model.relief_reader.read_relief``). Figures, pooled over the
materials: the mean squared error of the slope, its energy over the truth's, and its correlation
with the truth's; the materials' mean correlation. Entry ``relief_reader`` of
``results/model_quality.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, write_section

from mideepbasis.capturing.detail import fine_relief
from mideepbasis.model.checkpoint import load_model
from mideepbasis.model.relief_reader import from_normal_unit, load_reader, read_relief
from mideepbasis.train.relief_reader import ReliefTrainingConfig, slope_figures, validation_set


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reader", type=Path, action="append", default=[], metavar="FILE",
                        help="a relief reader's weights (repeatable)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "model_quality.json")
    args = parser.parse_args()
    torch.set_num_threads(2)
    config = ReliefTrainingConfig()
    items = validation_set(config)
    low = (config.band, config.band)
    model = load_model(None)
    rows = {}
    for scale in (1.0, 0.6):
        rows[f"normal unit x{scale:g}"] = slope_figures(
            lambda photo, light, fov: scale * fine_relief(model, photo, light[0], fov, low), items)
    start = from_normal_unit(model).eval()
    rows["the normal unit as one octave (a reader's start)"] = slope_figures(
        lambda photo, light, fov: read_relief(start, photo, light, fov, low), items)
    for path in args.reader:
        reader, document, _ = load_reader(path)
        rows[f"{path} (step {document.get('step')})"] = slope_figures(
            lambda photo, light, fov: read_relief(reader, photo, light, fov, low), items)
    print("| read by | mse | energy | correlation | mean correlation |\n|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['mse']:.5f} | {row['energy']:.3f} | {row['correlation']:+.3f} | "
              f"{row['mean_correlation']:+.3f} |")
    write_section(args.output, "relief_reader", "relief_reader", {"materials": len(items), "rows": rows})


if __name__ == "__main__":
    main()
