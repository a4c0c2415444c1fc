"""Capture time with capture's defaults against other capture options, alternated in one process.

    .venv/bin/python benchmarks/capture_ab.py --no-refine-unclamped-moves [--repeats 8]
    .venv/bin/python benchmarks/capture_ab.py --b-model runs/OTHER.safetensors      # two models, the same options
    .venv/bin/python benchmarks/capture_ab.py --photo PHOTO --resolution 1024 --no-fine-relief --a-resolution-too

Captures the bundled example photo (or ``--photo``) with capture's defaults (A) and with the capture options given
(B; any of ``mideepbasis capture``'s, as ``CaptureConfig`` reads them, and ``--b-model``), A and B taken in turn after
one untimed capture each (which records drjit's refinement step; ``--a-resolution-too``: A at B's
working resolution), and prints the median wall time
of each and their ratio: a change is judged by the ratio, never by seconds from another machine.
Writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import mideepbasis  # noqa: F401
from mideepbasis.capturing import CaptureConfig, Capturer
from mideepbasis.configs import add_config_arguments, config_from_arguments, given_fields
from mideepbasis.model.checkpoint import load_model
from mideepbasis.render.api import example_capture_dir


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--b-model", default=None, help="B's checkpoint (default: --model's)")
    parser.add_argument("--photo", type=Path, default=None,
                        help="the photo to capture (default: the bundled example photo, whose fine contrast the "
                             "relief test reads as albedo: the fine relief's unit does not run on it)")
    parser.add_argument("--a-resolution-too", action="store_true",
                        help="capture A at B's --resolution too, so that only the other options differ")
    add_config_arguments(parser, CaptureConfig, describe=False)
    args = parser.parse_args()
    model, photo = load_model(args.model), args.photo or example_capture_dir() / "photo.jpg"
    if not photo.is_file():
        parser.error(f"--photo {photo}: no such file")
    changes = [f"{name} {value}" for name, value in given_fields(args, CaptureConfig).items()]
    changes += [f"model {args.b_model}"] if args.b_model else []
    b_model = load_model(args.b_model) if args.b_model else model
    b_config = config_from_arguments(CaptureConfig, args)
    a_config = CaptureConfig(resolution=b_config.resolution) if args.a_resolution_too else CaptureConfig()
    a_name = f"A (defaults{f', resolution {a_config.resolution}' * args.a_resolution_too})"
    capturers = {a_name: Capturer(model, a_config),
                 f"B ({', '.join(changes) or 'the same'})": Capturer(b_model, b_config)}
    for capturer in capturers.values():
        capturer.capture(photo)
    seconds = {name: [] for name in capturers}
    for _ in range(args.repeats):
        for name, capturer in capturers.items():
            start = time.perf_counter()
            capturer.capture(photo)
            seconds[name].append(time.perf_counter() - start)
    medians = {name: statistics.median(values) for name, values in seconds.items()}
    for name, median in medians.items():
        print(f"{name}: median {median:.3f} s of {args.repeats}")
    first, second = medians.values()
    print(f"A / B: {first / second:.3f}")


if __name__ == "__main__":
    main()
