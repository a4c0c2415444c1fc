"""A batch on a Dask cluster against the local batch, on the same machine: photos per second.

    .venv/bin/python benchmarks/cluster.py [--photos 24] [--workers 2]

Captures ``--photos`` photos (the bundled photo turned and mirrored) as ``capture FOLDER`` does,
once with the local worker processes and once on a local Dask cluster of as many workers
(``--cluster local:N``), in fresh processes timed from outside; the rate counts the photos after
the first (the start-up, model loading included, is the first photo's). Written under the key
``cluster`` of ``results/capture.json`` (the capture benchmark's file).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import RESULTS, machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def make_photos(folder: Path, count: int) -> None:
    from PIL import Image

    photo = Image.open(ROOT / "mideepbasis" / "assets" / "example_capture" / "photo.jpg")
    variants = [photo.rotate(90 * k) for k in range(4)] + [photo.transpose(Image.FLIP_LEFT_RIGHT).rotate(90 * k)
                                                           for k in range(4)]
    for index in range(count):
        variants[index % len(variants)].save(folder / f"p{index:03d}.jpg", quality=95)


def timed(arguments: list[str]) -> tuple[float, list[float]]:
    """(wall time [s], the times since the start at which each photo's line appeared)."""
    started = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-m", "mideepbasis.cli", *arguments], stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True, cwd=ROOT)
    done = []
    for line in process.stdout:
        if " -> " in line:
            done.append(time.perf_counter() - started)
    process.wait()
    return time.perf_counter() - started, done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--photos", type=int, default=24)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        (folder / "in").mkdir()
        make_photos(folder / "in", args.photos)
        for name, extra in (("local", ["--workers", str(args.workers)]),
                            ("cluster", ["--cluster", f"local:{args.workers}"])):
            wall, done = timed(["capture", str(folder / "in"), "-o", str(folder / name), *extra])
            rate = (len(done) - 1) / (done[-1] - done[0]) if len(done) > 1 else 0.0
            rows[name] = {"wall_s": round(wall, 2), "first_photo_s": round(done[0], 2) if done else None,
                          "photos_per_s_after_first": round(rate, 3), "photos": len(done)}
            print(f"{name}: {wall:.1f} s, first photo {done[0]:.1f} s, {rate:.2f} photos/s after the first", flush=True)
    path = RESULTS / "capture.json"
    document = json.loads(path.read_text()) if path.is_file() else {"benchmark": "capture"}
    document["cluster"] = {"command": " ".join(sys.argv), "machine": machine(), "workers": args.workers,
                           "date": time.strftime("%Y-%m-%dT%H:%M:%S"), "rows": rows}
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(document, indent=2) + "\n")
    temporary.replace(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
