"""What every benchmark script shares: where results go, the machine, writing a report atomically."""

from __future__ import annotations

import datetime
import json
import os
import platform
from pathlib import Path

#: Folder of the JSON results (and figures) of the benchmarks.
RESULTS = Path(__file__).parent / "results"

#: The 84 shared test materials (../shared/data beside the repository; read-only, evaluation only).
SHARED_TEST = Path(__file__).resolve().parents[2] / "shared" / "data" / "deschaintre2018-test"


def machine() -> dict:
    """Platform, processor and core count of this machine."""
    import torch

    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "cuda": torch.cuda.is_available(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}


def write_report(path: Path, name: str, report: dict) -> Path:
    """Write ``report`` (with the benchmark's name, the date and the machine) as JSON, atomically."""
    document = {"benchmark": name, "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "machine": machine(), **report}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(document, indent=2) + "\n")
    temporary.replace(path)
    print(f"wrote {path}")
    return path


def save_figure(figure, path: Path, dpi: int = 90) -> Path:
    """Save a matplotlib figure as a PNG atomically (temporary file, then rename) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp.png")
    figure.savefig(temporary, dpi=dpi)
    plt.close(figure)
    temporary.replace(path)
    return path
