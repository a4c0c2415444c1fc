"""The height map's integration (``height.height_from_normals``): time and memory by map size.

    .venv/bin/python benchmarks/height.py [--sizes 1024 2048 4096] [--repeats 3] [--tileable]

Each size runs in a fresh interpreter (its peak resident memory is its own): a procedural
material's unit normals at that size, integrated ``--repeats`` times. Reported per size: the
median seconds and the peak resident memory the integration added over the normals already held
[MiB] (Linux's peak ``VmHWM``, restarted before the integrations, less the resident set then). Writes the entry
``height`` (``height_tileable`` with ``--tileable``) of results/capture.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys

from common import RESULTS, write_section

#: What one size's interpreter runs: argv size, repeats, tileable; prints its figures as JSON.
WORKER = """
import json, sys, time
import torch
from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.height import height_from_normals
size, repeats, tileable = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1"
normal = generate(3, config=GeneratorConfig(size=size, tileable=tileable)).to_tensor()[:3].contiguous()
def status(field):
    return int(open("/proc/self/status").read().split(field + ":")[1].split()[0]) / 1024
open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) restarts from the resident set now
before = status("VmRSS")
seconds = []
for _ in range(repeats):
    start = time.perf_counter()
    height = height_from_normals(normal, tileable)
    seconds.append(time.perf_counter() - start)
    del height
peak = status("VmHWM")
print(json.dumps({"seconds": seconds, "added_peak_mib": peak - before}))
"""


def measure(size: int, repeats: int, tileable: bool) -> dict:
    """One size's figures, from a fresh interpreter."""
    done = subprocess.run([sys.executable, "-c", WORKER, str(size), str(repeats), "1" if tileable else "0"],
                          check=True, capture_output=True, text=True)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    return {"size": size, "seconds_median": statistics.median(figures["seconds"]),
            "seconds": figures["seconds"], "added_peak_mib": round(figures["added_peak_mib"], 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tileable", action="store_true", help="integrate as periodic (a --tileable capture's)")
    parser.add_argument("-o", "--output", default=RESULTS / "capture.json")
    args = parser.parse_args()
    rows = []
    for size in args.sizes:
        rows.append(measure(size, args.repeats, args.tileable))
        print(f"{size} px: {rows[-1]['seconds_median']:.3f} s, +{rows[-1]['added_peak_mib']:.0f} MiB", flush=True)
    write_section(args.output, "height_tileable" if args.tileable else "height",
                  "height" + (" --tileable" if args.tileable else ""), {"repeats": args.repeats, "sizes": rows})


if __name__ == "__main__":
    main()
