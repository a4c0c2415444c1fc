"""What every benchmark script shares: where results go, the machine, writing a report atomically."""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import sys
from pathlib import Path

import numpy as np

#: Folder of the JSON results (and figures) of the benchmarks.
RESULTS = Path(__file__).parent / "results"

#: The 84 shared test materials (../shared/data beside the repository; read-only, evaluation only).
SHARED_TEST = Path(__file__).resolve().parents[2] / "shared" / "data" / "deschaintre2018-test"


#: The CPU's vector extensions that decide how quick torch and drjit's LLVM kernels are: the same
#: code ran its previews about 2.3 times slower on a 2 GHz AVX2 machine than on an AVX-512 one.
VECTOR_EXTENSIONS = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_bf16")


def cpu_description(cpuinfo: str | None = None) -> dict:
    """Model name, clock [MHz] and vector extensions of the first CPU in ``/proc/cpuinfo``
    (``cpuinfo``: its text; default read from the file; empty fields where there is none)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if not key:
            if fields:
                break  # the first processor's block only
            continue
        fields.setdefault(key, value.strip())
    flags = set(fields.get("flags", "").split())
    megahertz = fields.get("cpu MHz")
    return {"cpu_model": fields.get("model name"), "cpu_mhz": float(megahertz) if megahertz else None,
            "vector_extensions": [name for name in VECTOR_EXTENSIONS if name in flags]}


def machine() -> dict:
    """Platform, processor, its vector extensions and core count of this machine, and the Python
    interpreter (builds differ: pyenv's default one ran a capture 0.64 s slower than Debian's)."""
    import torch

    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "python": f"{platform.python_version()} {platform.python_compiler()}, {sys.base_prefix}",
            **cpu_description(), "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "cuda": torch.cuda.is_available(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "gomp_spincount": os.environ.get("GOMP_SPINCOUNT")}


def write_report(path: Path, name: str, report: dict) -> Path:
    """Write ``report`` (with the benchmark's name, the date, the command line and the machine) as
    JSON, atomically, keeping the entries other benchmarks wrote into the same file
    (``write_section``)."""
    document = {"benchmark": name, "date": datetime.datetime.now().isoformat(timespec="seconds"),
                "command": shlex.join(sys.argv), "machine": machine(), **report}
    path = Path(path)
    if path.is_file():
        try:
            earlier = json.loads(path.read_text())
        except json.JSONDecodeError:
            earlier = {}
        document.update({key: value for key, value in earlier.items()
                         if key not in document and isinstance(value, dict) and "benchmark" in value})
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(document, indent=2) + "\n")
    temporary.replace(path)
    print(f"wrote {path}")
    return path


def write_section(path: Path, key: str, name: str, report: dict) -> Path:
    """Write ``report`` (as ``write_report`` does: name, date, command line, machine) as the entry
    ``key`` of the JSON file ``path``, keeping its other entries: a benchmark that belongs beside
    another's figures, in the same file."""
    path = Path(path)
    document = json.loads(path.read_text()) if path.is_file() else {"benchmark": path.stem}
    document[key] = {"benchmark": name, "date": datetime.datetime.now().isoformat(timespec="seconds"),
                     "command": shlex.join(sys.argv), "machine": machine(), **report}
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(document, indent=2) + "\n")
    temporary.replace(path)
    print(f"wrote {key!r} of {path}")
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


def slope_correlation(normal: np.ndarray, luminance: np.ndarray) -> float:
    """Correlation of the log luminance's gradient with the relief's (the height's gradient from the
    normals, -n_x / n_z along columns, n_y / n_z along rows), both directions pooled: what a normal
    predictor reading the colours sees at the scale of pixels (positive: darker where the surface
    falls, darker is deeper). The height's correlation is dominated by broad relief instead."""
    z = np.clip(normal[2], 0.05, None)
    relief = np.stack([-normal[0] / z, normal[1] / z])[:, 2:-2, 2:-2]
    log_luminance = np.log(luminance + 1e-3)
    colour = np.stack([np.gradient(log_luminance, axis=1), np.gradient(log_luminance, axis=0)])[:, 2:-2, 2:-2]
    relief = relief - relief.mean(axis=(1, 2), keepdims=True)
    colour = colour - colour.mean(axis=(1, 2), keepdims=True)
    norm = np.sqrt((relief**2).sum() * (colour**2).sum())
    return float((relief * colour).sum() / norm) if norm > 1e-12 else 0.0


def run_generator_settings(path: Path) -> dict:
    """The procedural generator's settings of a training run (its config.json), as GeneratorConfig
    arguments."""
    try:
        procedural = json.loads(path.read_text())["procedural"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise SystemExit(f"{path}: not a training run's config.json with procedural settings ({error})")
    if not isinstance(procedural, dict):
        raise SystemExit(f"{path}: its procedural settings are {procedural!r}, not a table of settings")
    from mideepbasis.configs import drop_removed_fields

    try:  # a run's config may hold settings this version lacks, at their off values
        procedural = drop_removed_fields("GeneratorConfig", procedural, str(path))
    except ValueError as error:
        raise SystemExit(str(error))
    return {key: tuple(value) if isinstance(value, list) else value for key, value in procedural.items()}


def shared_predictions(model):
    """The shared test set's true maps (N, 10, H, W), ``evaluate``'s seeded hand-held offsets (N, 2)
    [patch half-widths] and ``model``'s maps (N, 10, H, W) predicted as ``evaluate``'s default
    protocol makes them (light known, no refinement, the network at its training resolution)."""
    from mideepbasis import constants
    from mideepbasis.capturing import RefineConfig
    from mideepbasis.evaluation.protocol import evaluation_offsets, load_evaluation_materials
    from mideepbasis.evaluation.run import predict_all

    if not SHARED_TEST.is_dir():
        raise SystemExit(f"{SHARED_TEST} is absent")
    fov = constants.DEFAULT_FOV_DEG
    truth = load_evaluation_materials(SHARED_TEST, "deschaintre5").maps
    offsets = evaluation_offsets(len(truth), 0, fov)
    predicted, _, _ = predict_all(model, truth, offsets, fov, "known", RefineConfig(steps=0), True, "model")
    return truth, offsets, predicted
