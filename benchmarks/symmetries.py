"""The prediction averaged over turns and mirrorings of the photo (``CaptureConfig.symmetries``):
quality against time, on held-out procedural materials and on the shared 84.

    .venv/bin/python benchmarks/symmetries.py [--model CKPT] [--counts 1 2 4 8] [--procedural 48]
    .venv/bin/python benchmarks/symmetries.py --chunks 2 4 8 [--repeats 7]

Quality: ``evaluate``'s default protocol (seeded hand-held offsets, light known, no refinement,
the network at its training resolution), map RMSE in the stored encoding and the re-rendering
RMSE under its 30 lights and views, for every count on the same photos. The procedural materials
(held-out seeds 3e9 + 900 on, the generator's defaults, 256 px) come first: a choice made there
is not made on the test set. Time: ``Capturer.predict`` of the bundled example photo at 256 px,
median of 7 after one untimed call. Stop any training run while it times (its figures are shared
with the machine's other work).

With ``--chunks``, only the time of the 8-symmetry prediction with each number of moved copies
run through the network at a time (``model.symmetry.SYMMETRY_CHUNK``): the chunks alternate in each
round (the order reversed every other round), ``--repeats`` rounds after one untimed call each,
and the largest difference of the maps from the first chunk's is reported (the chunking must not
change the prediction).

Both modes write benchmarks/results/symmetries.json.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import mideepbasis  # noqa: F401  (sets the OpenMP spin before torch loads)
import torch
from common import RESULTS, SHARED_TEST, write_report

from mideepbasis import constants
from mideepbasis.capturing import Capturer, CaptureConfig, Photo
from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.evaluation.metrics import map_rmse, rerender_rmse
from mideepbasis.evaluation.protocol import (RERENDER_COUNT, evaluation_offsets, flash_photos, load_evaluation_materials,
                                             random_lights_and_views)
from mideepbasis.render.api import example_capture_dir


def quality(capturer: Capturer, truth: torch.Tensor, counts: list[int], seed: int) -> dict:
    """Mean map and re-rendering RMSE of the predictions for each count of symmetries."""
    fov = constants.DEFAULT_FOV_DEG
    offsets = evaluation_offsets(len(truth), seed, fov)
    lights, views = random_lights_and_views(RERENDER_COUNT, seed)
    predicted = {count: [] for count in counts}
    for index in range(len(truth)):
        photos, _ = flash_photos(truth[index:index + 1], offsets[index:index + 1], fov, capturer.convention,
                                 capturer.model.config.plane_extent)
        photo = Photo(photos[0], fov, "argument")
        for count in counts:
            predicted[count].append(capturer.with_config(symmetries=count).predict(photo, offsets[index]).maps.cpu())
    report = {}
    for count, maps in predicted.items():
        maps = torch.cat(maps)
        errors = {name: float(value.mean()) for name, value in map_rmse(maps, truth).items()}
        errors["rerender"] = float(rerender_rmse(maps, truth, lights, views, capturer.convention).mean())
        report[str(count)] = errors
    return report


def timing(capturer: Capturer, counts: list[int], repeats: int = 7) -> dict:
    """Median seconds of one ``predict`` of the bundled photo (256 px) for each count."""
    photo = capturer.load(example_capture_dir() / "photo.jpg")
    seconds = {}
    for count in counts:
        predicting = capturer.with_config(symmetries=count)
        predicting.predict(photo, (0.25, -0.17)).maps
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            predicting.predict(photo, (0.25, -0.17)).maps
            times.append(time.perf_counter() - start)
        seconds[str(count)] = statistics.median(times)
    return seconds


def chunk_timing(capturer: Capturer, chunks: list[int], repeats: int) -> dict:
    """Median seconds of the bundled photo's 8-symmetry ``predict`` for each symmetry chunk, and
    each chunk's largest map difference from the first chunk's."""
    from mideepbasis.model import symmetry

    photo = capturer.load(example_capture_dir() / "photo.jpg")
    predicting = capturer.with_config(symmetries=8)
    shipped = symmetry.SYMMETRY_CHUNK
    times = {chunk: [] for chunk in chunks}
    differences = {}
    first = None
    try:
        for chunk in chunks:
            symmetry.SYMMETRY_CHUNK = chunk
            maps = predicting.predict(photo, (0.25, -0.17)).maps
            first = maps if first is None else first
            differences[chunk] = float((maps - first).abs().max())
        for round_index in range(repeats):
            for chunk in chunks if round_index % 2 == 0 else chunks[::-1]:
                symmetry.SYMMETRY_CHUNK = chunk
                start = time.perf_counter()
                predicting.predict(photo, (0.25, -0.17)).maps
                times[chunk].append(time.perf_counter() - start)
    finally:
        symmetry.SYMMETRY_CHUNK = shipped
    return {str(chunk): {"median_s": round(statistics.median(times[chunk]), 4),
                         "runs_s": [round(t, 4) for t in times[chunk]],
                         "largest_map_difference": differences[chunk]} for chunk in chunks}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 8], choices=[1, 2, 4, 8])
    parser.add_argument("--procedural", type=int, default=48, help="held-out procedural materials")
    parser.add_argument("--chunks", type=int, nargs="+", default=None,
                        help="time only the 8-symmetry prediction with these symmetry chunks")
    parser.add_argument("--repeats", type=int, default=7, help="rounds of --chunks")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "symmetries.json")
    args = parser.parse_args()
    if args.chunks:
        capturer = Capturer(args.model, CaptureConfig(fov=constants.DEFAULT_FOV_DEG))
        capturer.model.eval()
        report = {"model": args.model or "shipped", "chunks": chunk_timing(capturer, args.chunks, args.repeats)}
        for chunk, row in report["chunks"].items():
            print(f"chunk {chunk}: {1000 * row['median_s']:.0f} ms, maps differ by at most "
                  f"{row['largest_map_difference']:.1e}")
        write_report(args.output, "symmetries", report)
        return
    if not SHARED_TEST.is_dir():
        raise SystemExit(f"{SHARED_TEST} is absent")
    capturer = Capturer(args.model, CaptureConfig(fov=constants.DEFAULT_FOV_DEG))
    capturer.model.eval()
    generator = GeneratorConfig(size=256)
    procedural = torch.stack([generate(3 * 10**9 + 900 + i, config=generator).to_tensor()
                              for i in range(args.procedural)])
    shared = load_evaluation_materials(SHARED_TEST, "deschaintre5").maps
    report = {"model": args.model or "shipped", "counts": args.counts,
              "predict_seconds": timing(capturer, args.counts),
              "procedural": quality(capturer, procedural, args.counts, 11),
              "shared": quality(capturer, shared, args.counts, 0)}
    print("| symmetries | set | normal | diffuse | roughness | specular | re-render | predict [ms] |")
    print("|---|---|---|---|---|---|---|---|")
    for count in map(str, args.counts):
        for name in ("procedural", "shared"):
            row = report[name][count]
            print(f"| {count} | {name} | {row['normal']:.4f} | {row['diffuse']:.4f} | {row['roughness']:.4f} | "
                  f"{row['specular']:.4f} | {row['rerender']:.4f} | {1000 * report['predict_seconds'][count]:.0f} |")
    write_report(args.output, "symmetries", report)


if __name__ == "__main__":
    main()
