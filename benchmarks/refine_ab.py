"""Capture time with two refinement settings, alternated in one process on one machine.

    .venv/bin/python benchmarks/refine_ab.py [--b unclamped_moves=false] [--repeats 8]

Captures the bundled example photo with capture's defaults (A) and with the ``RefineConfig``
fields of ``--b`` changed (B), A and B taken in turn after one untimed capture each (which records
drjit's refinement step), and prints the median wall time of each and their ratio: a change is
judged by the ratio, never by seconds from another machine. Writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import mideepbasis  # noqa: F401
from mideepbasis.capturing import CaptureConfig, Capturer
from mideepbasis.model.checkpoint import load_model
from mideepbasis.render.api import example_capture_dir


def parse_fields(text: str, config) -> dict:
    """``name=value,...`` as field values of the dataclass ``config``, each cast to its field's type."""
    changes = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if not hasattr(config, name):
            raise SystemExit(f"refine_ab: --b: RefineConfig has no field {name!r}")
        current = getattr(config, name)
        changes[name] = value.lower() in ("1", "true", "yes") if isinstance(current, bool) else type(current)(value)
    return changes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--b", default="unclamped_moves=false", help="RefineConfig fields of B, as name=value,...")
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    args = parser.parse_args()
    model, photo, default = load_model(args.model), example_capture_dir() / "photo.jpg", CaptureConfig()
    changes = parse_fields(args.b, default.refine)
    capturers = {"A (default)": Capturer(model, default),
                 f"B ({args.b})": Capturer(model, dataclasses.replace(default, refine=dataclasses.replace(default.refine, **changes)))}
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
