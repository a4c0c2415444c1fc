"""Training data: generator speed, synthesis throughput, and coverage against the shared test set.

    .venv/bin/python benchmarks/data.py [--coverage-count 2000] [-o benchmarks/results/data.json]
    .venv/bin/python benchmarks/data.py --coverage-only --run-config runs/RUN/config.json -o OUT.json

Measures:
- generator speed at 256x256 on one core (torch and OpenCV limited to one thread) [materials/s],
  over all families and per family;
- synthesis throughput at 256x256 on this machine's cores [training pairs/s]: for given materials,
  M and M + xi rendered under a hand-held flash through the Mitsuba plugin, photographed (noise,
  gains, 8-bit sRGB) and turned into network inputs with their lighting marks; and the whole
  pipeline with the materials made by the loader training uses (``Trainer.loader``: two workers);
- coverage: histograms of each map's per-material mean and spread, and of normal tilt, for
  procedural materials beside the 84 shared test materials (../shared/data, skipped if absent),
  written to benchmarks/results/coverage.png (with ``-o OUT.json``: OUT.png beside it). Values are
  compared as the renderer uses them (linear; the test maps are used as stored, like the reference
  implementations do). With ``--run-config``, the procedural materials are drawn as that training
  run drew them (its undulation, gloss and darkening).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import time
from pathlib import Path

import mideepbasis  # noqa: F401  (sets the OpenMP spin before torch loads)
import numpy as np
import torch
from common import RESULTS, SHARED_TEST, run_generator_settings, save_figure, slope_correlation, write_report

from mideepbasis import constants


#: Targets of the issue.
TARGETS = {"generator_materials_per_second": 20.0, "synthesis_pairs_per_second": 16.0}


def one_core() -> None:
    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def generator_speed(count: int, size: int) -> dict:
    from mideepbasis.data.procedural import FAMILIES, generate

    one_core()
    generate(0, size=size)
    start = time.perf_counter()
    for seed in range(count):
        generate(10_000 + seed, size=size)
    overall = count / (time.perf_counter() - start)
    per_family = {}
    for name in FAMILIES:
        start = time.perf_counter()
        for seed in range(20):
            generate(20_000 + seed, size=size, family=name)
        per_family[name] = round(1e3 * (time.perf_counter() - start) / 20, 2)
    return {"materials_per_second": round(overall, 2), "ms_per_material_by_family": per_family,
            "materials": count, "size": size}


def synthesis_speed(batch: int, batches: int, size: int) -> dict:
    import tempfile

    from mideepbasis.data.procedural import generate
    from mideepbasis.data.synth import synthesize
    from mideepbasis.train import TrainConfig, Trainer

    torch.set_num_threads(os.cpu_count() or 1)
    maps = torch.stack([generate(seed, size=size).to_tensor() for seed in range(batch)])
    generator = torch.Generator().manual_seed(0)
    synthesize(maps, generator)  # compile the kernels
    start = time.perf_counter()
    for _ in range(batches):
        synthesize(maps, generator)
    pairs = batch * batches / (time.perf_counter() - start)

    # The loader training uses: TrainingMaterials by number through the step sampler, two workers.
    with tempfile.TemporaryDirectory() as folder:
        trainer = Trainer(TrainConfig(out=folder, preset="tiny", batch=batch, size=size, workers=2, validate_every=0),
                          progress=False)
        iterator = iter(trainer.loader())
        next(iterator)
        start = time.perf_counter()
        for _ in range(batches):
            synthesize(next(iterator), generator)
    pipeline = batch * batches / (time.perf_counter() - start)
    return {"pairs_per_second": round(pairs, 2), "pipeline_pairs_per_second_with_2_generator_workers": round(pipeline, 2),
            "batch": batch, "batches": batches, "size": size}


def height_from_normals(normal: np.ndarray) -> np.ndarray:
    """A height field (H, W) whose normals are ``normal`` (3, H, W), up to scale and offset
    (Frankot-Chellappa: the least-squares integrable surface, periodic boundaries). Rows run
    towards -y, as in ``height_to_normal``."""
    z = np.clip(normal[2], 0.05, None)
    d_dcol, d_drow = -normal[0] / z, normal[1] / z
    rows, cols = normal.shape[1:]
    u = 2 * np.pi * np.fft.fftfreq(cols)[None, :]
    v = 2 * np.pi * np.fft.fftfreq(rows)[:, None]
    denominator = u**2 + v**2
    denominator[0, 0] = 1.0
    spectrum = (-1j * u * np.fft.fft2(d_dcol) - 1j * v * np.fft.fft2(d_drow)) / denominator
    spectrum[0, 0] = 0.0
    return np.real(np.fft.ifft2(spectrum))


def _statistics(maps: np.ndarray) -> np.ndarray:
    """Per-material statistics: means and spreads of diffuse, roughness, specular, tilt [deg], the
    specular's colour (mean max - min over RGB), the correlation of the diffuse luminance with
    the height integrated from the normals (positive: brighter is higher, darker is deeper), and
    of their gradients (``slope_correlation``)."""
    normal, diffuse = maps[constants.NORMAL], maps[constants.DIFFUSE].mean(0)
    roughness, specular = maps[constants.ROUGHNESS][0], maps[constants.SPECULAR].mean(0)
    tilt = np.degrees(np.arccos(np.clip(normal[2], -1, 1)))
    chroma = (maps[constants.SPECULAR].max(0) - maps[constants.SPECULAR].min(0)).mean()
    height = height_from_normals(normal)
    if height.std() < 1e-6 or diffuse.std() < 1e-6:
        correlation = 0.0
    else:
        correlation = float(np.corrcoef(diffuse.ravel(), height.ravel())[0, 1])
    return np.array([diffuse.mean(), diffuse.std(), roughness.mean(), roughness.std(), specular.mean(),
                     specular.std(), tilt.mean(), np.percentile(tilt, 90), chroma, correlation,
                     slope_correlation(normal, diffuse)], np.float32)


def kinds(statistics: np.ndarray) -> dict:
    """Shares of the kinds of material the training data should hold, from ``_statistics`` rows."""
    diffuse, roughness, specular, chroma, correlation = (statistics[:, i] for i in (0, 2, 4, 8, 9))
    metal = (specular > 0.5) & (diffuse < 0.1)
    return {"metal (specular > 0.5, diffuse < 0.1)": round(float(metal.mean()), 3),
            "coloured metal (also specular max - min > 0.1)": round(float((metal & (chroma > 0.1)).mean()), 3),
            "glossy dielectric (roughness < 0.25, specular < 0.1)":
                round(float(((roughness < 0.25) & (specular < 0.1)).mean()), 3),
            "albedo follows relief (|corr(luminance, height)| > 0.3)": round(float((np.abs(correlation) > 0.3).mean()), 3),
            "darker is deeper (corr > 0.3)": round(float((correlation > 0.3).mean()), 3),
            "albedo independent of relief (|corr| < 0.1)": round(float((np.abs(correlation) < 0.1).mean()), 3),
            "darker is deeper, pixel scale (slope corr > 0.2)": round(float((statistics[:, 10] > 0.2).mean()), 3),
            "brighter is deeper, pixel scale (slope corr < -0.2)": round(float((statistics[:, 10] < -0.2).mean()), 3)}


def _procedural_statistics(seed: int, legacy_relief: bool = False, settings: dict | None = None) -> np.ndarray:
    from mideepbasis.data.procedural import GeneratorConfig, generate

    one_core()
    if settings is not None:
        config = GeneratorConfig(**{**settings, "size": 128})
    else:
        config = GeneratorConfig(size=128, relief_tilt_deg=None) if legacy_relief else GeneratorConfig(size=128)
    return _statistics(generate(seed, config=config).to_tensor().numpy())


STAT_NAMES = ["diffuse mean", "diffuse spread", "roughness mean", "roughness spread", "specular mean",
              "specular spread", "normal tilt mean [deg]", "normal tilt 90th percentile [deg]", "specular colour",
              "corr(luminance, height)", "corr(luminance slope, height slope)"]


def coverage(count: int, output: Path, legacy_relief: bool = False, settings: dict | None = None) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mideepbasis.data.datasets import DeschaintreDataset

    with multiprocessing.get_context("spawn").Pool(os.cpu_count() or 1) as pool:
        procedural = np.stack(pool.starmap(_procedural_statistics,
                                           [(seed, legacy_relief, settings) for seed in range(100_000, 100_000 + count)],
                                           chunksize=16))
    test = None
    if SHARED_TEST.is_dir():
        test = np.stack([_statistics(m.to_tensor().numpy()) for m in DeschaintreDataset(SHARED_TEST)])
    figure, axes = plt.subplots(2, 6, figsize=(24, 7))
    for index, (axis, name) in enumerate(zip(axes.ravel(), STAT_NAMES)):
        values = [procedural[:, index]] + ([test[:, index]] if test is not None else [])
        bins = np.linspace(min(v.min() for v in values), max(v.max() for v in values) + 1e-6, 40)
        axis.hist(procedural[:, index], bins=bins, density=True, alpha=0.6, label=f"procedural ({count})")
        if test is not None:
            axis.hist(test[:, index], bins=bins, density=True, alpha=0.6, label=f"shared test ({len(test)})")
        axis.set_title(name)
        axis.legend(fontsize=7)
    for axis in axes.ravel()[len(STAT_NAMES):]:
        axis.axis("off")
    figure.suptitle("Coverage of the procedural generator: per-material statistics of the maps (as the renderer uses them)")
    figure.tight_layout()
    save_figure(figure, output)

    def summary(values):
        return {name: [round(float(np.percentile(values[:, i], q)), 4) for q in (5, 50, 95)]
                for i, name in enumerate(STAT_NAMES)}

    result = {"figure": str(output), "procedural_count": count, "legacy_relief": legacy_relief,
              "generator_settings": settings,
              "procedural_percentiles_5_50_95": summary(procedural), "procedural_kinds": kinds(procedural)}
    if test is not None:
        result["test_count"] = len(test)
        result["test_percentiles_5_50_95"] = summary(test)
        result["test_kinds"] = kinds(test)
        # Share of test materials whose every statistic lies inside the procedural 1-99% range.
        low, high = np.percentile(procedural, 1, axis=0), np.percentile(procedural, 99, axis=0)
        result["test_inside_procedural_1_99_range"] = round(float(((test >= low) & (test <= high)).all(1).mean()), 3)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generator-count", type=int, default=200)
    parser.add_argument("--coverage-count", type=int, default=2000)
    parser.add_argument("--synthesis-batches", type=int, default=6)
    parser.add_argument("--coverage-only", action="store_true", help="skip the speed measurements")
    parser.add_argument("--legacy-relief", action="store_true",
                        help="coverage of the generator without relief scaling (bump_scale factor), for comparison")
    parser.add_argument("--run-config", type=Path,
                        help="coverage of the generator as a training run drew it (the run's config.json)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "data.json")
    args = parser.parse_args()
    settings = run_generator_settings(args.run_config) if args.run_config else None
    # The coverage figure: results/coverage.png for the default report, else OUT.png beside OUT.json.
    default_output = args.output.resolve() == (RESULTS / "data.json").resolve()
    figure = RESULTS / "coverage.png" if default_output else args.output.with_suffix(".png")

    report = {"targets": TARGETS}
    if args.coverage_only:
        report["coverage"] = coverage(args.coverage_count, figure, args.legacy_relief, settings)
        print("coverage:", json.dumps(report["coverage"], indent=1))
        write_report(args.output, "data", report)
        return
    report["synthesis"] = synthesis_speed(batch=16, batches=args.synthesis_batches, size=256)
    print("synthesis:", report["synthesis"])
    report["coverage"] = coverage(args.coverage_count, figure, args.legacy_relief, settings)
    print("coverage:", {k: v for k, v in report["coverage"].items() if "percentiles" not in k})
    report["generator"] = generator_speed(args.generator_count, 256)
    print("generator:", report["generator"])
    write_report(args.output, "data", report)


if __name__ == "__main__":
    main()
