"""Train several variants side by side on one lent GPU, inside a fixed wall-clock budget.

    python3 scripts/device_train.py --minutes 7.5 --out $OUT            # on the device machine

The variants share the seed, hence the very same materials, photos and order: a controlled
A/B at equal steps. Each is one ``mideepbasis train`` process (torch render backend, bfloat16
autocast); they share the GPU and split the CPU cores between their material workers. A short
calibration run measures the steps per second of all variants together, so that the cosine
schedule of the real runs ends when the budget does. What comes back under ``--out``: each
variant's ``best.safetensors`` (by held-out validation), its ``train.jsonl``, and ``device.log``;
with ``--final-only``, each variant's last weights in float16 and one ``train.jsonl`` of all
variants (four variants within the device tool's eight files and 64 MiB):

    python3 scripts/device_train.py --variants phone phone_highlight phone_highlight_local \
        phone_highlight_less_colour --minutes 6 --lr 5e-5 --local-lr 5e-5 --final-only --out $OUT

The real photos' highlight imprint (issue 43), the whole network from the shipped weights, a
control and three levers within the device tool's limits:

    python3 scripts/device_train.py --variants phone_no_falloff_highlight16_local phone_dark_glossy_local \
        phone_dark_glossy_lobe_local phone_dark_glossy_lobe_global_local \
        --init mideepbasis/models/deepbasis_compact.safetensors --minutes 7 --lr 5e-5 --local-lr 5e-5 --final-only --out $OUT

The script imports the package itself: run it with the repository root on ``PYTHONPATH``.
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

#: The phone-photo fine-tune's flags (the architecture of the shipped model spelt out, the
#: generator's relief, every phone lever of ``synth.PHONE_PHOTOS`` with 40 % plain batches).
PHONE_FINE_TUNE = [
    "--network-normal-unit-width", "16", "--network-normal-unit-blocks", "1,1,1,2",
    "--network-normal-unit-middle-blocks", "4", "--network-normal-unit-octaves", "1,0.5",
    "--network-normal-slope-scaled", "--network-extra-inputs", "view", "--render-weight", "0", "--vc-weight", "0",
    "--seed", "211", "--warmup-steps", "100", "--procedural-relief-tilt-deg", "1.5,30",
    "--procedural-coarse-relief-tilt-deg", "2.5,35", "--procedural-coarse-relief-probability", "0.85",
    "--synthesis-fov-range", "20,75", "--synthesis-cast-in-diffuse", "--synthesis-white-balance-sigma", "0.08",
    "--synthesis-tone-contrast", "0,0.6", "--synthesis-vignetting", "0,0.35", "--synthesis-flash-cone", "0,3",
    "--synthesis-jpeg-quality", "70,95", "--synthesis-tilt-deg", "4", "--synthesis-plain-probability", "0.4",
    "--train-only", "encoder,weight_decoder,global_unit"]


def without(flags: list[str], *options: str) -> list[str]:
    """``flags`` less each of ``options`` and the values that follow it (the tokens up to the
    next ``--`` flag)."""
    kept, dropping = [], False
    for token in flags:
        if token.startswith("--"):
            dropping = token in options
        if not dropping:
            kept.append(token)
    return kept


#: The phone fine-tune without the falloff levers.
PHONE_NO_FALLOFF = without(PHONE_FINE_TUNE, "--synthesis-vignetting", "--synthesis-flash-cone")


#: Darker and glossier materials than the generator's own (``GeneratorConfig.darkening_probability``,
#: ``gloss_probability``), as the local-unit runs of MODEL.md drew them.
DARK_GLOSSY = ["--procedural-gloss-probability", "0.45", "--procedural-darkening-probability", "0.75"]


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
    # Issue 43: the fine-tune on photos as phones take them (the CPU recipe of MODEL.md's "Tried"
    # table), from the shipped weights; give --lr 5e-5 --local-lr 5e-5.
    "phone": PHONE_FINE_TUNE,
    # The same with the diffuse loss weighted under the flash's highlight, against the leak.
    "phone_highlight": [*PHONE_FINE_TUNE, "--highlight-weight", "8"],
    # ... with the local unit trained too, so that it adapts to the encoder it is fed by.
    "phone_highlight_local": [*PHONE_FINE_TUNE, "--highlight-weight", "8",
                              "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # ... without the view input (stage 11's 9 input channels): does the view input let the
    # network fit a photo under a wrong flash, which biases the light search?
    "phone_highlight_noview": [*without(PHONE_FINE_TUNE, "--network-extra-inputs"), "--highlight-weight", "8"],
    # ... with fewer colour levers: a colour cast in the diffuse and a strong white-balance error
    # make the diffuse colour of a photo ambiguous.
    "phone_highlight_less_colour": [*without(PHONE_FINE_TUNE, "--synthesis-cast-in-diffuse"),
                                    "--synthesis-white-balance-sigma", "0.04", "--highlight-weight", "8"],
    # Without the falloff levers (vignetting, flash cone), which bias the light search (MODEL.md).
    "phone_no_falloff_highlight": [*PHONE_NO_FALLOFF, "--highlight-weight", "8"],
    # ... with the local unit trained too.
    "phone_no_falloff_highlight_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "8",
                                         "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # ... with the highlight weighted twice as much.
    "phone_no_falloff_highlight16_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16",
                                           "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # ... with fewer colour levers.
    "phone_no_falloff_highlight_less_colour": [*without(PHONE_NO_FALLOFF, "--synthesis-cast-in-diffuse"),
                                               "--synthesis-white-balance-sigma", "0.04", "--highlight-weight", "8"],
    # ... with more plain batches (60 %), closer to the renderer the light search fits with.
    "phone_no_falloff_highlight_plain60": [*PHONE_NO_FALLOFF, "--highlight-weight", "8",
                                           "--synthesis-plain-probability", "0.6"],
    # The real flash photos are darker and glossier than the generator's materials (the local unit's
    # diffuse deviations near their tanh bound: benchmarks/README.md, highlight_leak), and no run of
    # the local unit alone on the CPU lowered their highlight's imprint (MODEL.md, Tried): the whole
    # network on darker, glossier materials, beside phone_no_falloff_highlight16_local as control.
    "phone_dark_glossy_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # ... with the diffuse's loss on sRGB-encoded albedo, where a dark material's blob costs more.
    "phone_dark_glossy_encoded_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                        "--diffuse-loss-encoded",
                                        "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # ... with a phone's highlight compression (the real photos clip 0 - 1.4 % of their pixels).
    "phone_dark_glossy_compressed_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                           "--synthesis-highlight-compression", "1,8",
                                           "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # The diffuse makes up what the lobe misses of the highlight (benchmarks/README.md, highlight_leak): the
    # lobe's own miss under the photo's flash in the loss, and the local unit's error map as a log ratio that
    # does not clip where the global lobe overshoots.
    "phone_dark_glossy_lobe_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                     "--lobe-weight", "2",
                                     "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    "phone_dark_glossy_lobe_ratio_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                           "--lobe-weight", "2", "--network-error-map", "log_ratio",
                                           "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
    # The same with the global blend alone held to the truth's reflectance: the global bases a
    # material, the local unit's error map what they miss.
    "phone_dark_glossy_lobe_global_local": [*PHONE_NO_FALLOFF, "--highlight-weight", "16", *DARK_GLOSSY,
                                            "--lobe-weight", "2", "--global-weight", "0.5",
                                            "--train-only", "encoder,weight_decoder,global_unit,local_unit"],
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


def halved(source: Path, target: Path) -> None:
    """Write ``source``'s weights to ``target`` in float16, as ``ship_model.py --half`` does to every
    part (``load_model`` casts them back): a float32 checkpoint of the shipped network is over
    the 16 MiB a file that comes back from the device machine."""
    from ship_model import shipped_metadata  # this script's folder is on sys.path

    from mideepbasis.model.checkpoint import load_model, read_checkpoint, save_checkpoint

    model = load_model(source)
    document, _ = read_checkpoint(source)
    metadata = shipped_metadata(document, str(source), [name for name, _ in model.named_children()])
    save_checkpoint(target, model.half(), metadata=metadata)


def copy_results(runs: Path, out: Path, names: list[str], files=("best.safetensors", "train.jsonl"),
                 half: bool = False) -> None:
    """Copy each variant's weights and log into ``out`` (temporary file, then rename), so that
    a run killed at the call's time limit still brings back what it has; ``half``: the weights in
    float16, and every variant's log in one ``out / "train.jsonl"`` (a ``variant`` field in each
    record), to keep within the device tool's eight files."""
    logs = []
    for name in names:
        (out / name).mkdir(parents=True, exist_ok=True)
        for file in files:
            source = runs / name / file
            if not source.exists():
                continue
            if half and file == "train.jsonl":
                logs += [json.dumps({"variant": name, **json.loads(line)}) for line in source.read_text().splitlines()]
                continue
            target = out / name / file
            if target.exists() and target.stat().st_mtime >= source.stat().st_mtime:
                continue  # unchanged since the last copy
            temporary = out / name / f".{file}.tmp"
            if half and file.endswith(".safetensors"):
                halved(source, temporary)
            else:
                shutil.copy(source, temporary)
            os.replace(temporary, target)
    if logs:
        temporary = out / ".train.jsonl.tmp"
        temporary.write_text("\n".join(logs) + "\n")
        os.replace(temporary, out / "train.jsonl")


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
    parser.add_argument("--final-only", action="store_true",
                        help="bring back only the last weights, in float16, and the logs in one file (best.safetensors "
                             "while the runs last): four variants fit the device tool's limits")
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
    copy = lambda: copy_results(args.runs, args.out, args.variants, files, half=args.final_only)  # noqa: E731
    wait_all({name: launch(name, [*common, "--steps", str(steps), "--validate-every", str(max(50, steps // args.validations)),
                                  "--max-minutes", str(args.minutes)], args.runs, workers, log)
              for name in args.variants}, log, every=20.0, copy=copy)
    copy()
    if args.final_only:
        for name in args.variants:
            # A run stopped by --max-minutes leaves its last weights in its checkpoint alone.
            last = next((file for file in ("model.safetensors", "checkpoint.safetensors")
                         if (args.runs / name / file).exists()), None)
            if last is not None:
                halved(args.runs / name / last, args.out / name / "model.safetensors")
                (args.out / name / "best.safetensors").unlink(missing_ok=True)
                print(f"{name}: brought back its {last}", file=log, flush=True)
    for name in args.variants:
        run = args.runs / name
        final = [json.loads(line) for line in (run / "train.jsonl").read_text().splitlines()]
        validations = [r for r in final if "validation_score" in r]
        best = min(validations, key=lambda r: r["validation_score"]) if validations else None
        print(f"{name}: {final[-1].get('step')} steps; best validation {json.dumps(best)}", file=log, flush=True)
    print(f"done after {time.monotonic() - started:.0f} s", file=log, flush=True)


if __name__ == "__main__":
    main()
