"""Capture speed and memory: each stage at 256x256, the whole command, and 1024x1024.

    .venv/bin/python benchmarks/capture.py [--model PATH] [--repeats 5] [-o benchmarks/results/capture.json]

Every configuration runs in a fresh process (so its peak resident memory is its own) on the
bundled example photo, warm (one untimed capture first, which compiles the render kernels), and
reports the median wall time of the repeats [s]:

- ``known_light``: prediction with the flash offset given (no search, no refinement);
- ``search``: lighting search and prediction;
- ``search_refine``: lighting search, prediction and the default refinement (125 steps, normals kept);
- ``search_refine_paper``: the same with the paper's refinement (500 steps, normals refined too);
- ``command``: the whole ``mideepbasis capture`` command, start-up and all outputs included;
- ``search_refine_1024``: as ``search_refine`` with the photo processed at 1024x1024.

The command's runs happen in a child process of their own too, so the peak memory reported for
them (``RUSAGE_CHILDREN``: the largest of a process's children) is theirs alone.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402
TARGETS_S = {"known_light": 0.5, "search": 1.0, "search_refine": 3.0, "search_refine_paper": 3.0, "command": 6.0,
             "search_refine_1024": 15.0}
CONFIGURATIONS = {
    "known_light": {"light": (0.25, -0.17), "refine": {"steps": 0}, "resolution": 256},
    "search": {"light": None, "refine": {"steps": 0}, "resolution": 256},
    "search_refine": {"light": None, "resolution": 256},
    "search_refine_paper": {"light": None, "refine": {"steps": 500, "normals": True}, "resolution": 256},
    "search_refine_1024": {"light": None, "resolution": 1024},
}


def measure(name: str, model: str | None, repeats: int) -> dict:
    """Runs in a child process: times ``capture`` for one configuration."""
    import mideepbasis  # noqa: F401
    from mideepbasis.capture import CaptureConfig, Capturer, RefineConfig
    from mideepbasis.render.api import example_capture_dir

    photo = example_capture_dir() / "photo.jpg"
    settings = dict(CONFIGURATIONS[name])
    refine = RefineConfig(**settings.pop("refine", {}))
    capturer = Capturer(model, CaptureConfig(refine=refine, **settings))
    capturer.capture(photo)  # warm-up: kernels compiled
    runs, stages = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        result = capturer.capture(photo)
        runs.append(time.perf_counter() - start)
        stages.append(result.timings)
    median_stages = {stage: statistics.median(s[stage] for s in stages) for stage in stages[0]}
    return {"median_s": statistics.median(runs), "runs_s": [round(r, 3) for r in runs],
            "stages_median_s": {k: round(v, 3) for k, v in median_stages.items()},
            "peak_memory_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def measure_command(model: str | None, repeats: int) -> dict:
    """Times the whole command in fresh processes; the largest peak memory among them."""
    from mideepbasis.render.api import example_capture_dir

    photo = example_capture_dir() / "photo.jpg"
    runs, peak = [], 0.0
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as folder:
            command = [sys.executable, "-m", "mideepbasis.cli", "capture", str(photo), "-o", str(Path(folder) / "out")]
            if model:
                command += ["--model", model]
            start = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True)
            runs.append(time.perf_counter() - start)
            peak = max(peak, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
    return {"median_s": statistics.median(runs), "runs_s": [round(r, 3) for r in runs], "peak_memory_mib": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "capture.json")
    args = parser.parse_args()
    if args.child:
        child = measure_command if args.child == "command" else lambda *a: measure(args.child, *a)
        print(json.dumps(child(args.model, args.repeats)))
        return

    results = {}
    for name in [*CONFIGURATIONS, "command"]:
        repeats = args.repeats if "1024" not in name else max(2, args.repeats // 2)
        command = [sys.executable, __file__, "--child", name, "--repeats", str(repeats)]
        if args.model:
            command += ["--model", args.model]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        results[name] = json.loads(output.strip().splitlines()[-1])
        print(f"{name:20s} {results[name]['median_s']:.2f} s (target {TARGETS_S[name]} s), "
              f"peak {results[name]['peak_memory_mib']:.0f} MiB, stages {results[name].get('stages_median_s', '-')}")
    write_report(args.output, "capture", {"photo": "bundled example (512x512 JPEG)", "targets_s": TARGETS_S,
                                          "results": results})


if __name__ == "__main__":
    main()
