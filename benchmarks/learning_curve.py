"""The learning curve of the shipped model's lineage, every training stage in one PNG.

    .venv/bin/python benchmarks/learning_curve.py [--add LABEL runs/NAME/train.jsonl BATCH] [-o benchmarks/results/learning_curve.png]

Every training stage that led to (or continues from) the shipped weights keeps its validation
records in ``benchmarks/results/training/lineage.jsonl``: per stage, one line with its label,
batch size, steps and the materials seen before it (``"label"`` present), then its records
(each with its ``"stage"`` index). ``--add`` appends a stage, copying the validation records of
a run's log (and its speed records, as ``steps_per_second``); adding a label again (a resumed run,
further on) refreshes that stage in place. The curve plots held-out validation map RMSE (64 fixed
procedural materials at 128 px, in-memory encoding: normals as unit vectors) against the number
of training materials seen, beside the flat-normal RMSE.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from common import RESULTS, save_figure

#: Every stage of the lineage and its records, one JSON object a line.
LINEAGE = RESULTS / "training" / "lineage.jsonl"


def load_stages(path: Path | None = None) -> list[dict]:
    """The stages in order, each {label, batch, steps, start_materials, records} (``path``: default
    ``LINEAGE``)."""
    path = LINEAGE if path is None else path
    stages: list[dict] = []
    if not path.exists():
        return stages
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        entry = json.loads(line)
        index = entry.pop("stage")
        if "label" in entry:
            stages.append({**entry, "records": []})
        else:
            stages[index]["records"].append(entry)
    return stages


def save_stages(stages: list[dict], path: Path | None = None) -> None:
    path = LINEAGE if path is None else path
    lines = []
    for index, stage in enumerate(stages):
        lines.append({"stage": index, **{key: value for key, value in stage.items() if key != "records"}})
        lines += [{"stage": index, **record} for record in stage["records"]]
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(".jsonl.tmp")
    temporary.write_text("".join(json.dumps(line) + "\n" for line in lines))
    temporary.replace(path)


def kept_record(record: dict) -> dict | None:
    """What the lineage keeps of a training log's record: validation records whole, speed records
    as {step, steps_per_second}, nothing else."""
    if "validation_score" in record:
        return record
    rate = next((value for key, value in record.items() if key.endswith("steps_per_second")), None)
    return None if rate is None else {"step": record.get("step"), "steps_per_second": rate}


def add_stage(label: str, log: Path, batch: int, first_start: int = 0, start: int | None = None) -> None:
    """Append the validation records of ``log`` (a run of ``batch`` materials per step) as a stage
    after the existing ones; it starts where the last stage ended (the first at ``first_start``)
    or at ``start`` materials seen (a stage that continues from an earlier step's weights)."""
    stages = load_stages()
    records = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    previous = next((i for i, stage in enumerate(stages) if stage["label"] == label), None)
    if previous is not None:  # the same run, further on (a resumed run): its stage is refreshed in place
        start = stages[previous]["start_materials"] if start is None else start
        stages, tail = stages[:previous], stages[previous + 1:]
    else:
        tail = []
    if start is None:
        start = stages[-1]["start_materials"] + stages[-1]["steps"] * stages[-1]["batch"] if stages else first_start
    kept = [k for k in map(kept_record, records) if k is not None]
    steps = max((r["step"] for r in records if "step" in r), default=0)
    stages.append({"label": label, "batch": batch, "steps": steps, "start_materials": start, "records": kept})
    save_stages(stages + tail)


def plot(output: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = load_stages()
    stages_count = len(stages)
    # The legend goes under the panels (one line per stage), where it hides no curve.
    figure, axes = plt.subplots(1, 5, figsize=(20, 4 + 0.16 * stages_count))
    names = ["normal", "diffuse", "roughness", "specular"]
    for index, stage in enumerate(stages):
        colour = f"C{index}"
        validations = [r for r in stage["records"] if "validation_score" in r]
        x = [(stage["start_materials"] + r["step"] * stage["batch"]) / 1000 for r in validations]
        for axis, name in zip(axes, names):
            axis.plot(x, [r["validation_rmse"][name] for r in validations], marker=".", label=stage["label"],
                      color=colour)
        axes[0].plot(x, [r["validation_flat_normal_rmse"] for r in validations], "k:", linewidth=1)
        rerender = [(xi, r["validation_rerender_rmse"]) for xi, r in zip(x, validations) if "validation_rerender_rmse" in r]
        if rerender:
            axes[4].plot(*zip(*rerender), marker=".", label=stage["label"], color=colour)
    for axis, name in zip(axes, names + ["re-render (sRGB)"]):
        axis.set_title(f"{name} RMSE" + (" (dotted: flat)" if name == "normal" else ""))
        axis.set_xlabel("training materials seen [thousands]")
        axis.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=2, fontsize=7, frameon=False)
    figure.suptitle("held-out procedural validation (64 materials, 128 px), the shipped model's lineage")
    figure.tight_layout(rect=(0, 0.08 * stages_count / 5 + 0.02, 1, 1))
    save_figure(figure, output)
    print(f"wrote {output}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--add", nargs=3, metavar=("LABEL", "TRAIN_JSONL", "BATCH"), action="append", default=[],
                        help="append a stage: its label, its run's log and its batch size")
    parser.add_argument("--first-start", type=int, default=19_288,
                        help="materials seen before the first stage (the first shipped model: 2,411 CPU steps of 8)")
    parser.add_argument("--start", type=int, default=None,
                        help="materials seen before the stage added (default: where the last stage ended); "
                             "with one --add only, as it would apply to each")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "learning_curve.png")
    args = parser.parse_args()
    if args.start is not None and len(args.add) > 1:
        parser.error("--start names where one stage starts: give it with a single --add (one call per stage)")
    for label, log, batch in args.add:
        add_stage(label, Path(log), int(batch), args.first_start, args.start)
    plot(args.output)


if __name__ == "__main__":
    main()
