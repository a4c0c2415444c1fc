"""Capture speed and memory: each stage at 256x256, the whole command, and 1024x1024.

    .venv/bin/python benchmarks/capture.py [--model PATH] [--repeats 5] [-o benchmarks/results/capture.json]

Every configuration runs in a fresh process (so its peak resident memory is its own) on the
bundled example photo, warm (one untimed capture first, which compiles the render kernels), and
reports the median wall time of the repeats [s] and their median CPU time (user + system, all
threads; for the commands, their processes') [s]:

- ``known_light``: prediction with the flash offset given (no search, no refinement);
- ``search``: lighting search and prediction;
- ``search_refine``: lighting search, prediction and the default refinement (250 steps along the cosine, normals kept);
- ``search_refine_paper``: the same with the paper's refinement (500 steps at one rate, normals refined too);
- ``command``: the whole ``mideepbasis capture`` command, start-up and all outputs included;
  ``command_paper`` with the paper's refinement, ``command_1024`` and ``command_2048`` with the
  photo processed at that resolution (the capture targets are for these whole commands),
  ``command_no_shapes`` without the sphere and cloth previews (what those two images cost);
  ``command_phone_native`` on a phone's 12 MP frame (4032 x 3024 JPEG, the bundled photo
  upscaled and cropped, made first) at ``--resolution native``: 3024 px maps, a size that is no
  multiple of the network's;
- ``search_refine_1024``: as ``search_refine`` with the photo processed at 1024x1024 (in one
  process with earlier repeats, so its peak memory holds two captures);
- ``batch`` (``--batch N``, default 50): ``mideepbasis capture FOLDER -o OUT`` on N procedural
  flash photos at 256x256 (seeded, made first; 8-bit JPEG): the whole command's wall time, the
  photos per second after the first (from the moment each photo's line is printed), peak memory.

The command's runs happen in a child process of their own too, so the peak memory reported for
them (``RUSAGE_CHILDREN``: the largest of a process's children) is theirs, with one floor: Linux
keeps in a spawned child's peak the parent's at the spawn (this process, about 0.3 GB with torch
imported), below every command's own peak measured so far.

To compare with another build, check it out (``git worktree add /tmp/before REV``) and run this
script from that folder with ``PYTHONPATH=/tmp/before``: the commands run ``python -m
mideepbasis.cli``, which imports the package from the current folder before ``PYTHONPATH``.
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
TARGETS_S = {"known_light": 0.5, "search": 1.0, "search_refine": 1.2, "search_refine_paper": 4.0, "command": 3.0,
             "search_refine_1024": 5.0, "command_paper": 4.0, "command_1024": 5.0, "command_2048": 15.0,
             "command_4096": 80.0, "command_no_shapes": 3.0, "command_phone_native": 80.0}

#: Whole ``mideepbasis capture`` commands timed from outside: name -> options.
COMMANDS = {"command": (), "command_paper": ("--refine-steps", "500", "--refine-normals", "--refine-lr", "0.01",
                                             "--refine-lr-schedule", "constant"),
            "command_1024": ("--resolution", "1024"), "command_2048": ("--resolution", "2048"),
            "command_4096": ("--resolution", "4096"), "command_no_shapes": ("--no-shape-previews",),
            "command_phone_native": ("--resolution", "native")}

#: Commands run on a photo of their own instead of the bundled one: name -> (width, height) [pixels].
PHOTO_SIZES = {"command_phone_native": (4032, 3024)}
CONFIGURATIONS = {
    "known_light": {"light": (0.25, -0.17), "refine": {"steps": 0}, "resolution": 256},
    "search": {"light": None, "refine": {"steps": 0}, "resolution": 256},
    "search_refine": {"light": None, "resolution": 256},
    "search_refine_paper": {"light": None, "resolution": 256,
                            "refine": {"steps": 500, "normals": True, "lr": 0.01, "lr_schedule": "constant"}},
    "search_refine_1024": {"light": None, "resolution": 1024},
}


def measure(name: str, model: str | None, repeats: int) -> dict:
    """Runs in a child process: times ``capture`` for one configuration."""
    import mideepbasis  # noqa: F401
    from mideepbasis.capturing import CaptureConfig, Capturer, RefineConfig
    from mideepbasis.render.api import example_capture_dir

    photo = example_capture_dir() / "photo.jpg"
    settings = dict(CONFIGURATIONS[name])
    refine = RefineConfig(**settings.pop("refine", {}))
    capturer = Capturer(model, CaptureConfig(refine=refine, **settings))
    capturer.capture(photo)  # warm-up: kernels compiled
    runs, cpu, stages = [], [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        result = capturer.capture(photo)
        runs.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)  # every thread of this process
        stages.append(result.timings)
    median_stages = {stage: statistics.median(s[stage] for s in stages) for stage in stages[0]}
    return {"median_s": statistics.median(runs), "runs_s": [round(r, 3) for r in runs],
            "cpu_median_s": round(statistics.median(cpu), 3),
            "stages_median_s": {k: round(v, 3) for k, v in median_stages.items()},
            "peak_memory_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def phone_photo(path: Path, size: tuple[int, int]) -> Path:
    """The bundled photo upscaled (bicubic) to the width of ``size`` (width, height) and cropped to
    its height about the centre, written as a JPEG: a phone's frame of the same scene."""
    from PIL import Image

    from mideepbasis.render.api import example_capture_dir

    width, height = size
    square = Image.open(example_capture_dir() / "photo.jpg").convert("RGB").resize((width, width), Image.BICUBIC)
    top = (width - height) // 2
    square.crop((0, top, width, top + height)).save(path, quality=92)
    return path


def measure_command(model: str | None, repeats: int, extra: tuple[str, ...] = (),
                    photo_size: tuple[int, int] | None = None) -> dict:
    """Times the whole command (with the options ``extra``) in fresh processes, on the bundled photo or
    on a phone's frame of ``photo_size`` (``phone_photo``); the largest peak memory among them."""
    from mideepbasis.render.api import example_capture_dir

    with tempfile.TemporaryDirectory() as photos:  # the phone frame, where there is one
        photo = (phone_photo(Path(photos) / "phone.jpg", photo_size) if photo_size
                 else example_capture_dir() / "photo.jpg")
        runs, cpu, peak = [], [], 0.0
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as folder:
                command = [sys.executable, "-m", "mideepbasis.cli", "capture", str(photo),
                           "-o", str(Path(folder) / "out"), *extra]
                if model:
                    command += ["--model", model]
                start, before = time.perf_counter(), children_cpu_s()
                subprocess.run(command, check=True, capture_output=True)
                runs.append(time.perf_counter() - start)
                cpu.append(children_cpu_s() - before)
                peak = max(peak, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
    return {"median_s": statistics.median(runs), "runs_s": [round(r, 3) for r in runs],
            "cpu_median_s": round(statistics.median(cpu), 3), "peak_memory_mib": peak,
            **({"photo_size": list(photo_size)} if photo_size else {})}


def children_cpu_s() -> float:
    """User plus system CPU time of this process's finished children [s]."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def make_batch_photos(folder: Path, count: int, seed: int = 5) -> list[Path]:
    """``count`` flash photos (256x256 JPEG) of held-out procedural materials under seeded hand-held offsets."""
    import torch

    from mideepbasis import geometry
    from mideepbasis.data.procedural import GeneratorConfig, generate
    from mideepbasis.data.synth import SynthesisConfig, sample_offsets, simulate_photo
    from mideepbasis.imageio import write_image
    from mideepbasis.render import render_flash

    generator = torch.Generator().manual_seed(seed)
    paths = []
    for index in range(count):
        maps = generate(2_000_000 + index, config=GeneratorConfig(size=256)).to_tensor()[None]
        lights = geometry.light_positions(sample_offsets(1, generator)).view(1, 1, 3)
        photo = simulate_photo(render_flash(maps, lights)[:, 0], generator, SynthesisConfig())
        paths.append(write_image(folder / f"shot_{index:03d}.jpg", photo[0].permute(1, 2, 0).numpy(), encode_srgb=True))
    return paths


def measure_batch(model: str | None, count: int, extra: list[str]) -> dict:
    """Times ``capture FOLDER`` on ``count`` photos: wall, photos per second after the first, peak memory."""
    import os

    with tempfile.TemporaryDirectory() as folder:
        shots = Path(folder) / "shots"
        shots.mkdir()
        make_batch_photos(shots, count)
        command = [sys.executable, "-m", "mideepbasis.cli", "capture", str(shots), "-o", str(Path(folder) / "out"), *extra]
        if model:
            command += ["--model", model]
        start, before = time.perf_counter(), children_cpu_s()
        done = []
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"}) as process:
            for line in process.stdout:
                if ": flash offset " in line:
                    done.append(time.perf_counter() - start)
        wall = time.perf_counter() - start
        if process.returncode != 0 or len(done) != count:
            raise SystemExit(f"batch capture failed ({len(done)} of {count} photos)")
    rate = (count - 1) / (done[-1] - done[0]) if count > 1 else float("nan")
    return {"photos": count, "options": extra, "median_s": wall, "cpu_s": round(children_cpu_s() - before, 2),
            "first_photo_s": round(done[0], 2),
            "photos_per_second_after_first": round(rate, 3),
            "peak_memory_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--batch", type=int, default=50, help="photos of the batch measurement (0: skip it)")
    parser.add_argument("--only", nargs="+", default=None, help="measure only these (names above, batch, batch_shapes)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "capture.json")
    args = parser.parse_args()
    if args.child:
        if args.child.startswith("batch"):
            extra = ["--shape-previews"] if args.child == "batch_shapes" else []
            print(json.dumps(measure_batch(args.model, args.batch, extra)))
            return
        if args.child in COMMANDS:
            print(json.dumps(measure_command(args.model, args.repeats, COMMANDS[args.child],
                                             PHOTO_SIZES.get(args.child))))
            return
        child = lambda *a: measure(args.child, *a)  # noqa: E731
        print(json.dumps(child(args.model, args.repeats)))
        return

    results = {}
    names = [*CONFIGURATIONS, *COMMANDS] + (["batch", "batch_shapes"] if args.batch else [])
    for name in args.only or names:
        if name.startswith("batch"):
            # In a child of its own, so that the peak memory is the batch's (its command and workers).
            command = [sys.executable, __file__, "--child", name, "--batch", str(args.batch)]
            if args.model:
                command += ["--model", args.model]
            output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
            results[name] = json.loads(output.strip().splitlines()[-1])
            print(f"{name:20s} {results[name]['median_s']:.1f} s ({results[name]['cpu_s']:.1f} s CPU) for {args.batch} photos, "
                  f"{results[name]['photos_per_second_after_first']:.2f} photos/s after the first "
                  f"(target 1), peak {results[name]['peak_memory_mib']:.0f} MiB")
            continue
        large = any(size in name for size in ("1024", "4096", "phone"))
        repeats = max(2, args.repeats // 2) if large else args.repeats
        command = [sys.executable, __file__, "--child", name, "--repeats", str(repeats)]
        if args.model:
            command += ["--model", args.model]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        results[name] = json.loads(output.strip().splitlines()[-1])
        print(f"{name:20s} {results[name]['median_s']:.2f} s (target {TARGETS_S[name]} s), "
              f"CPU {results[name]['cpu_median_s']:.2f} s, peak {results[name]['peak_memory_mib']:.0f} MiB, "
              f"stages {results[name].get('stages_median_s', '-')}")
    if args.only and args.output.exists():  # a partial run updates the measurements it made
        results = {**json.loads(args.output.read_text()).get("results", {}), **results}
    write_report(args.output, "capture", {"photo": "bundled example (512x512 JPEG)", "targets_s": TARGETS_S,
                                          "batch_photos": args.batch, "results": results})


if __name__ == "__main__":
    main()
