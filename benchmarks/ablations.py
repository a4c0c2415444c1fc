"""Ablations under one reduced budget: no VC loss, no local, no global, no bases, and N in {1, 2, 5, 10, 20}.

    .venv/bin/python benchmarks/ablations.py [--steps 600] [--batch 4] [--size 64] [--out runs/ablations]

Every variant is trained from the same seed on the same procedural stream with the same budget
(steps, batch, resolution), then evaluated the same way on the 84 shared test materials resampled
to the training resolution (inputs under seeded hand-held offsets given to the model, no
refinement, 30 random lights and views). Writes benchmarks/ablations.md (the table beside the
paper's; the run's date and machine are in the JSON) and benchmarks/results/ablations.json. A
variant whose model already exists is not trained again (delete its folder to retrain).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, SHARED_TEST, write_report

from mideepbasis.evaluation import (PAPER_DEEPBASIS, RERENDER_COUNT, EvaluationConfig, load_evaluation_set,
                                    random_lights_and_views, resize_maps, run_evaluation, score, summary_scores,
                                    trivial_baseline)
from mideepbasis.train import TrainConfig, train

HERE = Path(__file__).parent

#: variant -> (network overrides, VC-loss weight or None for the default)
VARIANTS = {
    "full (N=10)": ({}, None),
    "no variation-consistency loss": ({}, 0.0),
    "no local bases": ({"use_local": False}, None),
    "no global bases": ({"use_global": False}, None),
    "no bases (direct)": ({"use_bases": False}, None),
    "N=1": ({"num_bases": 1}, None),
    "N=2": ({"num_bases": 2}, None),
    "N=5": ({"num_bases": 5}, None),
    "N=20": ({"num_bases": 20}, None),
}


#: Hand-written notes below this line of ablations.md survive a regeneration of the table.
NOTES_MARKER = "<!-- notes kept by ablations.py -->"


def trivial_row(size: int, convention: str = "physical") -> dict:
    """The trivial baseline (flat normal, the set's mean maps) scored as the variants are."""
    _, truth, _ = load_evaluation_set(SHARED_TEST, "deschaintre5")
    truth = torch.stack([resize_maps(m, size) for m in truth])
    lights, views = random_lights_and_views(RERENDER_COUNT, EvaluationConfig(data="").seed)
    metrics = score(trivial_baseline(truth).expand_as(truth), truth, lights, views, convention, None)
    return {**summary_scores({key: float(value.mean()) for key, value in metrics.items()}), "train_seconds": 0.0}


def slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").lower()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path("runs/ablations"))
    parser.add_argument("--only", nargs="*", default=None, help="variants to run (default: all)")
    parser.add_argument("--table-only", action="store_true",
                        help="write the table from the variants already evaluated in --out; train and evaluate nothing")
    args = parser.parse_args()

    rows = {}
    for name, (network, vc_weight) in VARIANTS.items():
        if args.only and name not in args.only:
            continue
        folder = args.out / slug(name)
        model = folder / "model.safetensors"
        timing = folder / "train_seconds.txt"
        evaluated = folder / "evaluation" / "summary.json"
        if args.table_only:
            if not evaluated.exists():
                continue
            summary = json.loads(evaluated.read_text())
        else:
            if not model.exists():
                started = time.perf_counter()
                config = TrainConfig(out=str(folder), preset="compact", network=network, steps=args.steps,
                                     batch=args.batch, size=args.size, workers=1, validate_every=0, seed=11,
                                     vc_weight=0.05 if vc_weight is None else vc_weight)
                train(config, progress=False)
                timing.write_text(f"{time.perf_counter() - started:.1f}\n")
            summary = run_evaluation(EvaluationConfig(data=str(SHARED_TEST), format="deschaintre5",
                                                      out=str(folder / "evaluation"), overwrite=True,
                                                      model=str(model), resolution=args.size), progress=False)
        rows[name] = {"maps_rmse": summary["maps_rmse"], "render_rmse": summary["render_rmse"],
                      "render_flip": summary["render_flip"],
                      "train_seconds": float(timing.read_text()) if timing.exists() else float("nan")}
        print(name, rows[name])

    if rows:
        rows["trivial baseline (no training)"] = trivial_row(args.size)
    budget = {"steps": args.steps, "batch": args.batch, "size": args.size, "preset": "compact", "data": "procedural"}
    write_report(RESULTS / "ablations.json", "ablations", {"budget": budget, "rows": rows})
    lines = ["# Ablations", "",
             f"Budget for every variant: compact preset, {args.steps} steps of {args.batch} procedural materials at "
             f"{args.size}x{args.size} (each seen twice with the variation-consistency loss), seed 11. Evaluation: "
             f"the 84 shared test materials resampled to {args.size}x{args.size}, seeded hand-held offsets given to the "
             "model, no refinement; map RMSE in the stored encoding, re-rendering RMSE and FLIP under 30 random "
             f"lights and views. Command: `.venv/bin/python benchmarks/ablations.py --steps {args.steps} --out {args.out}`.", "",
             "| variant | normal | diffuse | roughness | specular | render RMSE | FLIP | train [s] |",
             "|---|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        maps = row["maps_rmse"]
        lines.append(f"| {name} | {maps['normal']:.4f} | {maps['diffuse']:.4f} | {maps['roughness']:.4f} | "
                     f"{maps['specular']:.4f} | {row['render_rmse']:.4f} | {row['render_flip']:.4f} | {row['train_seconds']:.0f} |")
    lines.append(f"| paper: DeepBasis, full (122 scenes, 256 px, their budget) | {PAPER_DEEPBASIS['normal']:.3f} | "
                 f"{PAPER_DEEPBASIS['diffuse']:.3f} | {PAPER_DEEPBASIS['roughness']:.3f} | {PAPER_DEEPBASIS['specular']:.3f} | - | - | - |")
    missing = [name for name in VARIANTS if name not in rows and not (args.only and name not in args.only)]
    if missing:
        lines += ["", "Not trained and evaluated yet under this budget: " + ", ".join(missing) + "."]
    lines += ["", "The paper's own ablation rows are not reproduced here: its text is not available on this machine. "
              "The budget is far smaller than the paper's (400k steps on a GPU), so these rows compare the variants "
              "with each other, not with the paper."]
    table = HERE / "ablations.md"
    previous = table.read_text() if table.exists() else ""
    kept = previous.split(NOTES_MARKER, 1)[1].strip() if NOTES_MARKER in previous else ""
    lines += ["", NOTES_MARKER] + ([kept] if kept else [])
    table.write_text("\n".join(lines) + "\n")
    print(f"wrote {HERE / 'ablations.md'}")


if __name__ == "__main__":
    main()
