"""Two builds' whole ``mideepbasis capture`` commands, run by run in turn: a comparison that the
machine's drift cannot bias.

    git worktree add /tmp/before REV
    .venv/bin/python benchmarks/command_ab.py /tmp/before [--pairs 10] [-- CAPTURE OPTIONS]

This project's machine changes speed by a third within minutes, so two builds timed one after
the other (``capture.py`` in each) can differ by more than any change between them. Here each
pair runs the two builds' commands one after the other, which first in turn, on the bundled photo, each
``python -m mideepbasis.cli capture`` from its own folder (which imports that folder's package)
and timed from outside. Printed: the median wall time [s] of each build, the median of the
pairs' differences and how many pairs the change won; written to ``results/command_ab.json``.
One untimed command of each build first (drjit's kernel cache, the file cache).
``--before-python`` runs the other build with another interpreter (two interpreters, one build:
``command_ab.py . --before-python /other/venv/bin/python``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, write_report  # noqa: E402

HERE = Path(__file__).resolve().parents[1]

#: The bundled photo, inside each build's own package.
PHOTO = Path("mideepbasis") / "assets" / "example_capture" / "photo.jpg"


def timed_command(folder: Path, out: Path, options: list[str], python: str = sys.executable) -> float:
    """Wall time [s] of one capture command run from ``folder`` by the interpreter ``python``."""
    command = [python, "-m", "mideepbasis.cli", "capture", str(folder / PHOTO), "-o", str(out),
               "--overwrite", *options]
    start = time.perf_counter()
    environment = {**os.environ, "PYTHONPATH": str(folder)}
    subprocess.run(command, check=True, capture_output=True, cwd=folder, env=environment)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path, help="the other build's checkout (a git worktree)")
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--before-python", default=sys.executable,
                        help="the interpreter that runs the other build (default: this one)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "command_ab.json")
    arguments, options = sys.argv[1:], []
    if "--" in arguments:
        arguments, options = arguments[:arguments.index("--")], arguments[arguments.index("--") + 1:]
    args = parser.parse_args(arguments)
    builds = {"before": args.before.resolve(), "after": HERE}
    pythons = {"before": args.before_python, "after": sys.executable}
    for name, folder in builds.items():
        if not (folder / PHOTO).is_file():
            raise SystemExit(f"{folder}: not a mideepbasis checkout (no {PHOTO})")
    times = {name: [] for name in builds}
    with tempfile.TemporaryDirectory() as scratch:
        for name, folder in builds.items():
            timed_command(folder, Path(scratch) / name, options, pythons[name])
        for index in range(args.pairs):
            # Which goes first alternates: the second of two commands ran quicker, the same build
            # both times (0.23 s in the median of 8 pairs).
            for name, folder in list(builds.items())[::1 if index % 2 == 0 else -1]:
                times[name].append(timed_command(folder, Path(scratch) / name, options, pythons[name]))
            print(f"pair {index + 1}: before {times['before'][-1]:.2f} s, after {times['after'][-1]:.2f} s")
    differences = [after - before for before, after in zip(times["before"], times["after"])]
    summary = {name: statistics.median(values) for name, values in times.items()}
    won = sum(difference < 0 for difference in differences)
    print(f"median: before {summary['before']:.2f} s, after {summary['after']:.2f} s; "
          f"median difference {statistics.median(differences):+.2f} s; after quicker in {won} of {args.pairs} pairs")
    write_report(args.output, "command_ab", {"before": str(builds["before"]), "pythons": pythons, "options": options,
                                             "times_s": times, "median_s": summary,
                                             "median_difference_s": statistics.median(differences),
                                             "pairs_won_by_after": won})


if __name__ == "__main__":
    main()
