"""Where one ``mideepbasis capture`` command's time goes: a timeline of its stages.

    .venv/bin/python benchmarks/command_timeline.py [--runs 2] [-- CAPTURE OPTIONS]

Each run is a fresh process that imports the package (torch's import in it) and the
command-line module, wraps the stages (model loading, search, prediction, refinement, writing,
each preview's scene and render, the report) with time marks, and runs ``cli.main`` on the
bundled photo as the console command does (torch started without its tracing modules, Mitsuba's
Python integrators left out, ``render.SKIP_PYTHON_INTEGRATORS``; the start-up's objects frozen,
``startup``). The marks are seconds since the process started its first import. Printed per
run: the time of each part (the package's import, the rest of start-up, each stage, the
previews' renders and the scenes between them), how many of the cores each stage kept busy (its
CPU time over its wall time: 2 is both), and ``results/command_timeline.json``. Options
after ``--`` go to ``capture`` (``-- --resolution 1024``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402

#: ``mideepbasis.startup.DEFER_TRACING_ENV`` (not imported here: the package imports torch).
DEFER_TRACING_ENV = "MIDEEPBASIS_DEFER_TORCH_TRACING"

#: The first part: the package's import, torch's import in it (as in the console command).
IMPORT = "import mideepbasis"

#: (module, attribute) of the functions marked, by the name printed.
MARKED = {"model": ("mideepbasis.capturing.pipeline", "Capturer.__init__"),
          "search": ("mideepbasis.capturing.pipeline", "Capturer.search"),
          "predict": ("mideepbasis.capturing.pipeline", "Capturer.predict"),
          "refine": ("mideepbasis.capturing.pipeline", "Capturer.refine"),
          "write": ("mideepbasis.export", "save_capture"),
          "render": ("mideepbasis.render.scenes", "render"),
          "report_page": ("mideepbasis.reporting", "write_report_page")}


def child(output: str, options: list[str]) -> None:
    """One command with its marks; writes [(seconds, event, name)] to ``output``."""
    import functools
    import importlib
    import time

    start = time.perf_counter()
    marks = []

    def mark(event: str, name: str) -> None:
        times = os.times()  # the process's CPU time, all its threads
        marks.append((time.perf_counter() - start, event, name, times.user + times.system))

    import mideepbasis  # noqa: F401  (torch's import in it, as in the console command)

    mark("end", IMPORT)
    import mideepbasis.cli as cli

    cli.prepare_console_process()  # as cli.run does

    for name, (module_name, attribute) in MARKED.items():
        owner = importlib.import_module(module_name)
        holder, _, function_name = attribute.rpartition(".")
        holder = getattr(owner, holder) if holder else owner
        function = getattr(holder, function_name)

        def wrapped(*args, _function=function, _name=name, **kwargs):
            mark("start", _name)
            try:
                return _function(*args, **kwargs)
            finally:
                mark("end", _name)

        setattr(holder, function_name, functools.wraps(function)(wrapped))
    from mideepbasis.render.api import example_capture_dir

    with tempfile.TemporaryDirectory() as folder:
        status = cli.main(["capture", str(example_capture_dir() / "photo.jpg"), "-o", str(Path(folder) / "out"),
                           *options])
    mark("end", "command")
    Path(output).write_text(json.dumps({"status": status, "marks": marks}))
    sys.stdout.flush()
    os._exit(0)  # as the console command ends


def parts(marks: list) -> dict[str, float]:
    """The parts of a run [s] from its marks: the package's import, the start-up before the model,
    each stage, the previews' renders together and the writing outside them."""
    first = {}
    last = {}
    renders = 0.0
    opened = None
    for seconds, event, name, *_ in marks:
        if event == "start":
            first.setdefault(name, seconds)
            opened = seconds if name == "render" else opened
        else:
            last[name] = seconds
            if name == "render" and opened is not None:
                renders += seconds - opened
    result = {IMPORT: last[IMPORT], "other start-up": first["model"] - last[IMPORT]}
    for name in ("model", "search", "predict", "refine", "write"):
        if name in first:
            result[name] = last[name] - first[name]
    result["previews' renders"] = renders
    if "render" in first:
        result["write: before the first render"] = first["render"] - first["write"]
        result["write: after the last render"] = last["write"] - last["render"]
    result["total"] = last["command"]
    return {name: round(value, 3) for name, value in result.items()}


def cores_busy(marks: list) -> dict[str, float]:
    """Each stage's CPU time over its wall time [cores]: how much of the two cores it keeps busy
    (the package's import from the process's start)."""
    opened = {}
    result = {IMPORT: marks[0][3] / max(marks[0][0], 1e-9)}
    for seconds, event, name, cpu in marks:
        if event == "start":
            opened.setdefault(name, (seconds, cpu))
        elif name in opened and name != "render":  # the stages, each marked once (three renders)
            wall0, cpu0 = opened[name]
            result[name] = (cpu - cpu0) / max(seconds - wall0, 1e-9)
    last = marks[-1]
    result["total"] = last[3] / max(last[0], 1e-9)
    return {name: round(value, 2) for name, value in result.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "command_timeline.json")
    args, options = parser.parse_known_args()
    options = [option for option in options if option != "--"]
    if args.child:
        child(args.child, options)
        return
    runs = []
    for index in range(args.runs):
        with tempfile.TemporaryDirectory() as folder:
            marks_file = Path(folder) / "marks.json"
            # The capture command's torch start-up (startup.tracing_modules_deferred), which this
            # script's own command line would not get.
            subprocess.run([sys.executable, __file__, "--child", str(marks_file), *options], check=True,
                           capture_output=True, env={**os.environ, DEFER_TRACING_ENV: "1"})
            run = json.loads(marks_file.read_text())
        if run["status"] != 0:
            raise SystemExit(f"the capture command failed (status {run['status']})")
        runs.append({"parts_s": parts(run["marks"]), "cores_busy": cores_busy(run["marks"]), "marks": run["marks"]})
        print(f"run {index + 1}: " + ", ".join(f"{name} {value:.2f}" for name, value in runs[-1]["parts_s"].items()))
        print("  cores busy: " + ", ".join(f"{name} {value:.2f}" for name, value in runs[-1]["cores_busy"].items()))
    write_report(args.output, "command_timeline", {"options": options, "runs": runs})


if __name__ == "__main__":
    main()
