"""The ``mideepbasis`` command. Thin: parse arguments, call the library, print one line per error.

    mideepbasis capture PHOTO [PHOTO ...] -o OUT [--fov DEG] [--light TX,TY] [--refine-steps 250]
                        [--refine-normals] [--resolution N|native] [--model PATH] [--exr] [--overwrite]
                        [--workers N] [every other CaptureConfig field: --search-grid, --refine-lr, ...]
    mideepbasis render MATERIAL_DIR -o OUT.exr [--light flash|env] [--fov 45] [--offset TX,TY]
                       [--spp N] [--convention physical|deepbasis] [--env studio|sunsky|FILE]
    mideepbasis demo [-o OUT_DIR]
    mideepbasis data preview [--n 64] [--seed S] [--family NAME] [--tileable] -o SHEET.png
    mideepbasis evaluate --data PATH --format deschaintre5|deschaintre4|folder [--model PATH]
                         [--light known|search] [--refine-steps K] [--refine-normals] [--baselines] [--lighting] -o OUT
    mideepbasis import-weights GLOBAL.pth LOCAL.pth --fov 45 -o model.safetensors
    mideepbasis train --out runs/NAME [--resume] [--preset compact] [--data procedural,FOLDER] [--steps N]
                      [every other TrainConfig field: --batch, --network-num-bases, --synthesis-fov, ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import sys
import warnings
from pathlib import Path

from . import constants
from .errors import InputError, MideepbasisError
from .startup import freeze_startup_objects


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


#: Each sub-command's line in ``mideepbasis --help``.
COMMAND_HELP = {
    "render": "render a material folder under the flash or an environment",
    "capture": "capture materials from flash photos",
    "demo": "capture the bundled example photo and compare with its ground truth",
    "data": "training data: look at the procedural generator",
    "evaluate": "evaluate a model on a dataset with the paper's protocol",
    "import-weights": "import the DeepBasis authors' published weights",
    "train": "train DeepBasisNet on synthesised flash photos",
}


def _add_render(subparsers, describe: bool = True, brief: bool = False) -> None:
    from .configs import add_config_arguments
    from .render.api import RenderConfig

    parser = subparsers.add_parser(
        "render", help=COMMAND_HELP["render"], usage="mideepbasis render MATERIAL_DIR -o OUT.exr [options]",
        formatter_class=_HelpFormatter,
        description="Render a material folder (docs/ARCHITECTURE.md section 6). "
                    "Writes the linear EXR and an sRGB PNG beside it. "
                    "With --light flash and no --spp, renders the per-pixel flash formula exactly; "
                    "with --spp, path traces the flash scene.")
    parser.add_argument("material", type=Path, metavar="MATERIAL_DIR", help="material folder (normal, diffuse, roughness, specular)")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.exr", help="output EXR; the PNG goes beside it")
    # Every RenderConfig field is an option (--light, --spp, --env, ...), documented by the field.
    add_config_arguments(parser, RenderConfig, describe=describe)
    parser.set_defaults(run=_run_render)


def _run_render(args) -> None:
    from .configs import config_from_arguments
    from .material import Material
    from .render.api import RenderConfig, render_with, write_render

    if args.output.suffix.lower() != ".exr":
        raise InputError(f"output {args.output} must end in .exr (the sRGB PNG is written beside it)")
    material = Material.load(args.material)
    image = render_with(material, config_from_arguments(RenderConfig, args))
    exr, png = write_render(image, args.output)
    print(f"wrote {exr} and {png}")


#: Photo suffixes a folder given to ``capture`` is searched for.
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".heic", ".heif", ".exr")


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's help, its lines broken between words only, never inside an option's name."""

    def _split_lines(self, text, width):
        import textwrap

        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)

    def _fill_text(self, text, width, indent):
        import textwrap

        return textwrap.fill(" ".join(text.split()), width, initial_indent=indent, subsequent_indent=indent,
                             break_on_hyphens=False)


#: The options each command's brief --help explains (the others are listed by name: --help-all).
BRIEF_HELP = {
    "capture": {"fov", "light", "resolution", "network_resolution", "symmetries", "tileable", "crop", "refine.steps",
                "refine.normals"},
    "evaluate": {"format", "input_photo", "overwrite", "model", "light", "refine.steps", "refine.normals",
                 "symmetries", "baselines", "lighting", "limit", "resolution", "environment"},
    "train": {"data", "steps", "batch", "size", "lr", "local_lr", "vc_weight", "seed", "workers", "validate_every",
              "device", "init", "train_only", "max_minutes", "bf16", "select_by"},
}


def _add_capture(subparsers, describe: bool = True, brief: bool = False) -> None:
    from .capturing import CaptureConfig
    from .configs import add_config_arguments

    parser = subparsers.add_parser(
        "capture", help=COMMAND_HELP["capture"], usage="mideepbasis capture PHOTO [PHOTO ...] -o OUT [options]",
        formatter_class=_HelpFormatter,
        description="Photo to material: lighting search, DeepBasis prediction, refinement of the global bases. "
                    "One photo writes the material folder into OUT; several (or a folder) write OUT/<photo name>/ each.")
    parser.add_argument("photos", type=Path, nargs="+", metavar="PHOTO", help="JPEG, PNG or EXR flash photos, or folders of them")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT")
    # Every CaptureConfig field is an option (--refine-steps, --search-grid, ...), documented by the field.
    add_config_arguments(parser, CaptureConfig, describe=describe, shown=BRIEF_HELP["capture"] if brief else None)
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--exr", action="store_true", help="also write the maps as linear EXR")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing OUT that the tool wrote (its manifest lists all it holds)")
    parser.add_argument("--preview-tiles", type=float, default=2.0,
                        help="times the maps repeat across the sphere and cloth previews")
    parser.add_argument("--viewer-screenshot", action="store_true",
                        help="also write viewer.png: report.html as headless Chromium shows it (needs chromium)")
    parser.add_argument("--shape-previews", action=argparse.BooleanOptionalAction, default=None,
                        help="path trace the material on a sphere and a draped cloth too (default: for one photo, "
                             "not for several)")
    parser.add_argument("--cluster", default=None, metavar="ADDRESS|local:N",
                        help="send the photos to a Dask distributed cluster (its scheduler's address, or local:N to "
                             "start one of N workers here); OUT and the photos must be on a file system every "
                             "worker reaches")
    parser.add_argument("--workers", type=_positive_int, default=None,
                        help="worker processes for several photos (default: one per core); each loads the model once")
    parser.add_argument("--truth", type=Path, default=None, metavar="MATERIAL",
                        help="a material folder of the photographed surface: also render it in the environment "
                             "(environment_truth.png, environment_difference.png); one photo only")
    parser.set_defaults(run=_run_capture)


def _photos(paths: list[Path]) -> list[Path]:
    photos = []
    for path in paths:
        if path.is_dir():
            photos += sorted(p for p in path.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
        else:
            photos.append(path)
    return photos


def _run_capture(args) -> int:
    from .capturing import CaptureConfig, Capturer
    from .configs import config_from_arguments
    from .export import save_capture
    from .outputs import OutputFolder

    photos = _photos(args.photos)
    if not photos:
        raise InputError(f"no photos ({', '.join(PHOTO_SUFFIXES)}) in {', '.join(str(p) for p in args.photos)}")
    single = len(photos) == 1
    truth = None
    if args.truth is not None:
        from .material import Material

        if not single:
            raise InputError("--truth compares one capture with its true material: give one photo")
        truth = Material.load(args.truth)
    inputs = photos + ([args.truth] if args.truth is not None else [])
    config = config_from_arguments(CaptureConfig, args)
    if not single or args.cluster:
        return _capture_batch(photos, args, config)
    # Checked and locked before the work: a refusal comes first, and no other command writes it meanwhile.
    folder = OutputFolder(args.output, overwrite=args.overwrite, inputs=inputs)
    from .batch import memory_note

    note = memory_note(photos[0], config)
    if note:
        print(f"mideepbasis: note: {photos[0].name}: {note}")
    try:
        capturer = Capturer(args.model, config)
        result = capturer.capture(photos[0], progress=True)
    except BaseException:
        folder.abort()
        raise
    result.output = None  # the network's tensors are not written; at 1024 px they hold 0.4 GB
    save_capture(result, folder, exr=args.exr, progress=True, truth=truth,
                 preview_tiles=args.preview_tiles, shape_previews=args.shape_previews is not False)
    if args.viewer_screenshot:
        _viewer_screenshot(args.output)
    for note in result.notes:
        print(f"mideepbasis: note: {photos[0].name}: {note}")
    print(f"{photos[0].name}: flash offset {result.offset_angle_deg:.1f} deg, "
          f"{sum(result.timings.values()):.1f} s -> {args.output}")
    return 0


def _capture_batch(photos: list[Path], args, config) -> int:
    """Several photos: worker processes (``batch``) or a cluster's workers (``cluster``), one line per
    photo as it completes."""
    from tqdm import tqdm

    from .batch import SaveOptions, capture_batch

    failures = 0
    options = SaveOptions(exr=args.exr, preview_tiles=args.preview_tiles, shape_previews=bool(args.shape_previews))
    # Checked on the call, before the progress bar: a refusal is one line.
    if args.cluster:
        from .cluster import cluster_batch

        items = cluster_batch(photos, args.output, args.cluster, args.model, config, options, overwrite=args.overwrite)
    else:
        from .batch import batch_workers

        workers = args.workers
        if workers is None:
            workers, note = batch_workers(photos, config)
            if note:
                print(f"mideepbasis: note: {note}")
        items = capture_batch(photos, args.output, args.model, config, options, workers, overwrite=args.overwrite)
    for item in tqdm(items, total=len(photos), desc="capturing", unit="photo"):
        if item.repeated:  # a cluster's task run again after its worker died, the folder written before
            tqdm.write(f"{item.photo.name}: written by this batch already -> {item.target}")
            continue
        if item.error is not None:
            failures += 1
            tqdm.write(f"mideepbasis: skipped {item.photo}: {item.error}")
            continue
        if args.viewer_screenshot:
            _viewer_screenshot(item.target)
        for note in item.notes:
            tqdm.write(f"mideepbasis: note: {item.photo.name}: {note}")
        tqdm.write(f"{item.photo.name}: flash offset {item.offset_angle_deg:.1f} deg, {item.seconds:.1f} s -> {item.target}")
    print(f"captured {len(photos) - failures} of {len(photos)} photos into {args.output}"
          + (f"; {failures} failed" if failures else ""))
    return 1 if failures else 0


def _viewer_screenshot(folder: Path) -> None:
    from .viewer import find_chromium, screenshot

    if find_chromium() is None:
        warnings.warn("--viewer-screenshot: no Chromium on this machine (Debian: apt-get install chromium); skipped")
        return
    screenshot(folder / "report.html", folder / "viewer.png")


def _add_demo(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help=COMMAND_HELP["demo"],
        description="Runs `capture` on a flash photo that ships with the package (rendered from a procedural "
                    "material with a hand-held offset) and prints the error against its ground truth.")
    parser.add_argument("-o", "--output", type=Path, default=Path("demo"), metavar="OUT_DIR")
    parser.add_argument("--model", type=Path, default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing, non-empty OUT_DIR")
    parser.set_defaults(run=_run_demo)


def _run_demo(args) -> None:
    import json

    from .capturing import capture
    from .evaluation import light_error_deg, map_rmse
    from .export import save_capture
    from .material import Material
    from .outputs import OutputFolder
    from .render.api import example_capture_dir
    from .resampling import downsample_maps

    folder = example_capture_dir()
    truth_light = json.loads((folder / "truth.json").read_text())
    output = OutputFolder(args.output, overwrite=args.overwrite)  # before the work, and only what it wrote
    try:
        result = capture(folder / "photo.jpg", model=args.model, progress=True)
    except BaseException:
        output.abort()
        raise
    save_capture(result, output, progress=True)
    for note in result.notes:
        print(f"note: {note}")
    truth = Material.load(folder / "truth").to_tensor()[None]
    truth = downsample_maps(truth, result.material.width)
    errors = {name: float(value[0]) for name, value in map_rmse(result.material.to_tensor()[None], truth).items()}
    light_error = light_error_deg(result.offset, truth_light["offset"], result.fov)
    print(f"captured {folder / 'photo.jpg'} into {args.output} in {sum(result.timings.values()):.1f} s")
    print(f"flash: found {result.offset_angle_deg:.1f} deg off centre, true offset off by {light_error:.2f} deg")
    print("map RMSE against the ground truth: " + ", ".join(f"{k} {v:.3f}" for k, v in errors.items()))
    print(f"open {args.output / 'report.html'} to see the maps, the re-rendering and the environment rendering")


def _add_data(subparsers) -> None:
    parser = subparsers.add_parser("data", help=COMMAND_HELP["data"])
    commands = parser.add_subparsers(dest="data_command", required=True)
    preview = commands.add_parser("preview", help="contact sheet of procedural materials (flash render and four maps each)")
    preview.add_argument("--n", type=_positive_int, default=64, help="number of materials")
    preview.add_argument("--seed", type=int, default=0, help="seed of the first material (the others follow)")
    preview.add_argument("--size", type=_positive_int, default=256, help="material resolution [pixels]")
    preview.add_argument("--family", default=None, help="only this family (default: all)")
    preview.add_argument("--tileable", action="store_true", help="make tileable materials")
    preview.add_argument("-o", "--output", type=Path, required=True, metavar="SHEET.png")
    preview.set_defaults(run=_run_data_preview)
    scenes = commands.add_parser("scenes", help="calibrated scenes of procedural materials photographed as a phone "
                                                "would: the real-photo protocol's validation set (evaluate --data)")
    scenes.add_argument("--n", type=_positive_int, default=24, help="number of scenes")
    scenes.add_argument("--seed", type=int, default=0, help="number of the first scene (the others follow)")
    scenes.add_argument("--size", type=_positive_int, default=256, help="side of the photos [pixels]")
    scenes.add_argument("-o", "--output", type=Path, required=True, metavar="OUT")
    scenes.add_argument("--overwrite", action="store_true", help="replace an existing OUT that the tool wrote")
    scenes.set_defaults(run=_run_data_scenes)


def _run_data_preview(args) -> None:
    from .data.preview import procedural_sheet
    from .data.procedural import FAMILIES

    if args.family is not None and args.family not in FAMILIES:
        raise InputError(f"unknown family {args.family!r}; known: {', '.join(sorted(FAMILIES))}")
    try:
        path = procedural_sheet(args.n, args.seed, args.output, size=args.size, tileable=args.tileable,
                                family=args.family)
    except ValueError as error:  # the generator's own check of its settings (e.g. a size too small)
        raise InputError(f"data preview: {error}") from None
    print(f"wrote {path}")


def _run_data_scenes(args) -> None:
    from .data.scenes import make_scenes
    from .outputs import OutputFolder

    with OutputFolder(args.output, overwrite=args.overwrite, kind="scenes") as folder:
        make_scenes(folder.staging, args.n, args.seed, args.size)
    print(f"wrote {args.n} calibrated scenes into {args.output}")


def _add_evaluate(subparsers, describe: bool = True, brief: bool = False) -> None:
    from .configs import add_config_arguments
    from .evaluation import EvaluationConfig

    parser = subparsers.add_parser(
        "evaluate", help=COMMAND_HELP["evaluate"], usage="mideepbasis evaluate --data FOLDER -o OUT [options]",
        formatter_class=_HelpFormatter,
        description="Synthetic data (the paper's protocol): inputs re-rendered from the ground-truth maps under a "
                    "seeded hand-held flash per material; map RMSE in the stored encoding; re-rendering RMSE, FLIP, "
                    "SSIM (and LPIPS when its weights are on this machine) under 30 seeded random lights and views. "
                    "Calibrated real scenes (the paper's Table 2): the material captured from one photo re-renders "
                    "the others (docs/ARCHITECTURE.md section 13).")
    parser.add_argument("--data", type=Path, required=True, help="dataset folder")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="OUT")
    # Every other EvaluationConfig field is an option (--refine-steps, --symmetries, ...), documented by the field.
    add_config_arguments(parser, EvaluationConfig, skip={"data", "out"}, defaults=EvaluationConfig(data=""),
                         describe=describe, shown=BRIEF_HELP["evaluate"] if brief else None)
    parser.set_defaults(run=_run_evaluate)


def _run_evaluate(args) -> None:
    from .configs import config_from_arguments
    from .evaluation import EvaluationConfig, run_evaluation

    if not args.data.is_dir():
        raise InputError(f"{args.data}: no such dataset folder")
    base = EvaluationConfig(data=str(args.data), out=str(args.output))
    config = config_from_arguments(EvaluationConfig, args, base)
    summary = run_evaluation(config)
    print((args.output / "table.md").read_text())
    for note in summary["notes"]:
        print(f"note: {note}")
    if config.data_format == "calibrated":
        print(f"{summary['n_scenes']} scenes in {summary['seconds']:.0f} s; wrote {args.output}")
        return
    print(f"{summary['n_materials']} materials ({summary['skipped']} skipped) in {summary['seconds']:.0f} s; "
          f"wrote {args.output}")


def _add_import_weights(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-weights", help=COMMAND_HELP["import-weights"],
        description="Map the authors' net_g_*.pth and net_l_*.pth (PyTorch state dicts, loaded without unpickling "
                    "code) onto the paper preset and write a mideepbasis checkpoint (deepbasis shading convention).")
    parser.add_argument("global_weights", type=Path, metavar="GLOBAL.pth")
    parser.add_argument("local_weights", type=Path, metavar="LOCAL.pth")
    parser.add_argument("--fov", type=float, required=True,
                        help="field of view the weights were trained for [deg]: 45 for *_2.414.pth, 28.07 for *_4.pth")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="model.safetensors")
    parser.set_defaults(run=_run_import_weights)


def _run_import_weights(args) -> None:
    from .model.checkpoint import import_authors_weights

    path = import_authors_weights(args.global_weights, args.local_weights, args.fov, args.output)
    print(f"wrote {path}: use it with --model in capture and evaluate")


def _add_train(subparsers, describe: bool = True, brief: bool = False) -> None:
    from .configs import add_config_arguments
    from .model.network import PRESETS
    from .train import TrainConfig

    parser = subparsers.add_parser("train", help=COMMAND_HELP["train"],
                                   usage="mideepbasis train --out runs/NAME [--resume] [options]",
                                   formatter_class=_HelpFormatter,
                                   description="Train DeepBasisNet (L_sup + 0.05 L_vc). Launch under torchrun for "
                                               "several processes; --resume continues a killed run exactly, with "
                                               "its stored settings (options given must agree with them).")
    parser.add_argument("--out", type=Path, required=True, metavar="runs/NAME", help="output folder of the run")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=argparse.SUPPRESS,
                        help="network preset the --network-* settings start from (default: compact)")
    # Every other TrainConfig field is an option (--steps, --network-num-bases, --synthesis-read-noise, ...).
    add_config_arguments(parser, TrainConfig, skip={"out", "preset", "synthesis.convention", "procedural.size"},
                         describe=describe, shown=BRIEF_HELP["train"] if brief else None)
    parser.set_defaults(run=_run_train)


def _run_train(args) -> None:
    from .configs import config_from_arguments
    from .model.checkpoint import read_checkpoint
    from .train import TrainConfig, train

    checkpoint = args.out / "checkpoint.safetensors"
    if args.resume:
        # The run's own settings; the options given replace them (and must agree where it matters).
        document, _ = read_checkpoint(checkpoint)
        try:
            base = TrainConfig.from_dict(document["training"]["config"], str(checkpoint), document.get("network"))
        except InputError:
            raise  # names the file and the setting already
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(f"{checkpoint}: its stored training settings cannot be read ({error})") from None
        if "preset" in args and args.preset != base.preset:
            raise InputError(f"{checkpoint}: this run was started with preset = {base.preset!r}, not {args.preset!r}")
    else:
        if checkpoint.exists():
            raise InputError(f"{args.out} already holds a run: pass --resume to continue it or choose another --out")
        base = TrainConfig(preset=getattr(args, "preset", TrainConfig.preset))
    config = config_from_arguments(TrainConfig, args, base)
    path = train(dataclasses.replace(config, out=str(args.out)), resume=args.resume)
    if path.exists():
        print(f"wrote {path}")
        return
    best = args.out / "best.safetensors"
    print(f"stopped before step {config.steps} (--max-minutes): continue with --resume"
          + (f"; best weights so far in {best}" if best.exists() else
             f"; the weights so far are in {checkpoint} (no validation ran: --validate-every 0)"))


def build_parser(command: str | None = None, describe: bool = True, brief: bool = False) -> argparse.ArgumentParser:
    """The command line's parser. Given the ``command`` about to run, the other sub-commands get
    only their name and help line: building them imports what they need (train's parser alone
    took 0.2 s of a capture's start). ``describe`` False leaves out the help of the options made
    from config fields (``add_config_arguments``), for a command line that prints no help;
    ``brief`` explains only the ``BRIEF_HELP`` options (``--help``; ``--help-all`` explains all)."""
    parser = argparse.ArgumentParser(prog="mideepbasis", description="SVBRDF capture from one hand-held flash photo.")
    subparsers = parser.add_subparsers(dest="command", required=True)
    adders = {"render": _add_render, "capture": _add_capture, "demo": _add_demo, "data": _add_data,
              "evaluate": _add_evaluate, "import-weights": _add_import_weights, "train": _add_train}
    for name, add in adders.items():
        if command in adders and name != command:
            subparsers.add_parser(name, help=COMMAND_HELP[name])
        elif name in _DESCRIBED_COMMANDS:
            add(subparsers, describe, brief)
        else:
            add(subparsers)
    return parser


#: The sub-commands whose options are made from config fields (their help read from the source).
_DESCRIBED_COMMANDS = ("capture", "evaluate", "render", "train")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    every_option = "--help-all" in argv
    argv = ["--help" if argument == "--help-all" else argument for argument in argv]
    wants_help = any(argument in ("-h", "--help") for argument in argv)
    args = build_parser(argv[0] if argv else None, describe=wants_help, brief=not every_option).parse_args(argv)
    warnings.formatwarning = lambda message, category, *rest: f"mideepbasis: warning: {message}\n"
    try:
        status = args.run(args)
    except (MideepbasisError, FileNotFoundError) as error:
        print(f"mideepbasis: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mideepbasis: interrupted", file=sys.stderr)
        return 130
    return status or 0


def prepare_console_process() -> None:
    """What the console command sets for its own process before ``main``: rendering without
    Mitsuba's Python integrators (``render.SKIP_PYTHON_INTEGRATORS``, unless the environment says
    otherwise) and the start-up's objects out of later garbage collections
    (``startup.freeze_startup_objects``)."""
    os.environ.setdefault(constants.SKIP_MITSUBA_PYTHON_INTEGRATORS_ENV, "1")
    freeze_startup_objects()


def _terminated(signal_number, frame) -> None:
    raise SystemExit(128 + signal_number)


def run() -> None:
    """The console command: ``main``, then a quick exit with its status.

    By the time ``main`` returns, every output is written, closed and renamed into place, and the
    worker processes and writer threads are joined. The interpreter's own teardown (freeing
    torch's and drjit's modules and thread pools) would still take about 0.5 s of a capture's 6 on
    this machine's two cores, for nothing: the streams are flushed and the process ends. Tests
    call ``main``, which returns. The command's rendering leaves out Mitsuba's Python integrators
    (``render.SKIP_PYTHON_INTEGRATORS``), which none of them uses.
    """
    prepare_console_process()
    # A terminated command unwinds as an interrupted one does: its workers stopped, its staged
    # output removed, the old output kept.
    signal.signal(signal.SIGTERM, _terminated)
    status = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


if __name__ == "__main__":
    run()
