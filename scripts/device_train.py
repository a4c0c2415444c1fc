"""Train several variants side by side on one lent GPU, inside a fixed wall-clock budget.

    python3 scripts/device_train.py --minutes 7.5 --out $OUT            # on the device machine

The variants share the seed, hence the very same materials, photos and order: a controlled
A/B at equal steps. Each is one ``mideepbasis train`` process (torch render backend, bfloat16
autocast); they share the GPU and split the CPU cores between their material workers. A short
calibration run measures the steps per second of all variants together, so that the cosine
schedule of the real runs ends when the budget does. What comes back under ``--out``: each
variant's ``best.safetensors`` (by held-out validation), its ``train.jsonl``, and ``device.log``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

#: Variant name -> extra ``train`` flags. All share COMMON.
VARIANTS = {
    "map": ["--render-weight", "0"],
    "render1": ["--render-weight", "1"],
    "render3": ["--render-weight", "3"],
    # Issue 11 section 1: input channels that make the shading explicit (widened from a 9-channel --init).
    "shading": ["--render-weight", "0", "--network-extra-inputs", "shading"],
    "shading_highpass": ["--render-weight", "0", "--network-extra-inputs", "shading,highpass"],
    # A wider local unit (started afresh, the rest from --init): it fitted two materials' normals
    # to 0.014 in 300 steps where the shipped width 8 reached 0.066.
    "local16": ["--render-weight", "0", "--network-local-width", "16"],
    "local24": ["--render-weight", "0", "--network-local-width", "24"],
    # The normal unit (relief inputs, a slope shared by the bases): alone, the rest frozen as
    # --init loaded it, and trained with everything else (MODEL.md).
    "normal_unit": ["--render-weight", "0", "--vc-weight", "0", "--network-normal-unit-width", "16",
                    "--train-only", "normal_unit"],
    "normal_unit_all": ["--render-weight", "0", "--network-normal-unit-width", "16"],
    # The same on materials with a broad undulation under their relief, which the shared test set
    # has and the generator's defaults lack (MODEL.md).
    "normal_unit_coarse": ["--render-weight", "0", "--vc-weight", "0", "--network-normal-unit-width", "16",
                           "--train-only", "normal_unit", "--procedural-coarse-relief-tilt-deg", "1.5,30"],
    "coarse_all": ["--render-weight", "0", "--network-normal-unit-width", "16",
                   "--procedural-coarse-relief-tilt-deg", "1.5,30"],
}

COMMON = ["--preset", "compact", "--data", "procedural", "--render-backend", "torch", "--bf16",
          "--seed", "11", "--validation-count", "64", "--warmup-steps", "200", "--grad-clip", "1.0",
          "--checkpoint-minutes", "1000", "--log-every", "20"]


def launch(name: str, flags: list[str], out: Path, workers: int, log) -> subprocess.Popen:
    command = [sys.executable, "-m", "mideepbasis.cli", "train", *COMMON, *VARIANTS[name], *flags,
               "--workers", str(workers), "--out", str(out / name)]
    print(" ".join(command), file=log, flush=True)
    environment = {**os.environ, "OMP_NUM_THREADS": "2", "PYTHONUNBUFFERED": "1", "TQDM_DISABLE": "1"}
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=environment)


def copy_results(runs: Path, out: Path, names: list[str], files=("best.safetensors", "train.jsonl")) -> None:
    """Copy each variant's best weights and log into ``out`` (temporary file, then rename), so that
    a run killed at the call's time limit still brings back what it has."""
    for name in names:
        (out / name).mkdir(parents=True, exist_ok=True)
        for file in files:
            source = runs / name / file
            if source.exists():
                temporary = out / name / f".{file}.tmp"
                shutil.copy(source, temporary)
                os.replace(temporary, out / name / file)


def wait_all(processes: dict, log, every: float = 0.0, copy=None) -> None:
    """Wait for every process, calling ``copy`` every ``every`` seconds meanwhile (0: never)."""
    while every and any(process.poll() is None for process in processes.values()):
        time.sleep(every)
        copy()
    for name, process in processes.items():
        code = process.wait()
        print(f"{name}: exit {code}", file=log, flush=True)
        if code != 0:
            raise SystemExit(f"variant {name} failed with exit code {code}; see the log")


def rate(run: Path) -> float:
    """Steps per second of a run, start-up excluded (the last ``process_steps_per_second`` record of
    its train.jsonl: the training process's steps since its first one)."""
    records = [json.loads(line) for line in (run / "train.jsonl").read_text().splitlines()]
    return [r["process_steps_per_second"] for r in records if "process_steps_per_second" in r][-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=7.5, help="wall time of the real runs [minutes]")
    parser.add_argument("--calibration-minutes", type=float, default=0.75)
    parser.add_argument("--variants", nargs="+", default=["normal_unit_coarse", "coarse_all", "normal_unit_all"],
                        choices=list(VARIANTS))
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--local-lr", type=float, default=1.5e-3)
    parser.add_argument("--init", default="mideepbasis/models/deepbasis_compact.safetensors")
    parser.add_argument("--validations", type=int, default=12, help="validations over the real run")
    parser.add_argument("--workers", type=int, default=0, help="material workers per variant (0: share the cores)")
    parser.add_argument("--keep-final", action="store_true",
                        help="bring back the last weights too (model.safetensors; mind the 8-file limit)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu to try the script on a small machine")
    parser.add_argument("--size", type=int, default=128, help="training resolution [pixels]")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--runs", type=Path, default=Path("/tmp/device_runs"))
    args = parser.parse_args()

    args.out.mkdir(parents=True, exist_ok=True)
    log = open(args.out / "device.log", "a")
    workers = args.workers or max(1, (os.cpu_count() or 4) // len(args.variants) - 1)
    print(f"cpus {os.cpu_count()}, {workers} workers per variant, variants {args.variants}", file=log, flush=True)
    shutil.rmtree(args.runs, ignore_errors=True)
    common = ["--device", args.device, "--size", str(args.size), "--batch", str(args.batch), "--lr", str(args.lr), "--local-lr", str(args.local_lr), "--init", args.init]

    started = time.monotonic()
    calibration = args.runs / "calibration"
    wait_all({name: launch(name, [*common, "--steps", "100000", "--validate-every", "0",
                                  "--max-minutes", str(args.calibration_minutes)], calibration, workers, log)
              for name in args.variants}, log)
    steps_per_second = min(rate(calibration / name) for name in args.variants)
    # Validations and start-up take some of the budget: aim the schedule at 92% of it.
    steps = max(100, int(steps_per_second * args.minutes * 60 * 0.92))
    print(f"calibration: {steps_per_second:.2f} steps/s (slowest variant) after {time.monotonic() - started:.0f} s; "
          f"{steps} steps", file=log, flush=True)

    files = ("best.safetensors", "train.jsonl") + (("model.safetensors",) if args.keep_final else ())
    copy = lambda: copy_results(args.runs, args.out, args.variants, files)  # noqa: E731
    wait_all({name: launch(name, [*common, "--steps", str(steps), "--validate-every", str(max(50, steps // args.validations)),
                                  "--max-minutes", str(args.minutes)], args.runs, workers, log)
              for name in args.variants}, log, every=20.0, copy=copy)
    copy()
    for name in args.variants:
        run = args.runs / name
        final = [json.loads(line) for line in (run / "train.jsonl").read_text().splitlines()]
        validations = [r for r in final if "validation_score" in r]
        best = min(validations, key=lambda r: r["validation_score"]) if validations else None
        print(f"{name}: {final[-1].get('step')} steps; best validation {json.dumps(best)}", file=log, flush=True)
    print(f"done after {time.monotonic() - started:.0f} s", file=log, flush=True)


if __name__ == "__main__":
    main()
