"""The evaluation's report: summary.json, per_material.csv, table.md and its figures (bars,
gallery, the environment comparisons, the lighting search's accuracy), written by ``run``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..imageio import write_image
from ..reporting import map_tiles, save_figure


def write_evaluation(out: Path, summary: dict, names: list[str], per_material: dict, predictions: dict,
                     truth: torch.Tensor, main_row: str, environment_scores=None) -> None:
    """summary.json, per_material.csv, table.md, bars.png and gallery.png in ``out`` (each written
    atomically); with environment scores also their columns in per_material.csv, their table in
    table.md, env_bars.png and env_gallery.png."""
    import csv
    import io
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..imageio import write_bytes
    from .protocol import PAPER_DEEPBASIS

    write_bytes(out / "summary.json", (json.dumps(summary, indent=2) + "\n").encode())
    if environment_scores is not None:
        per_material = {row: dict(values) for row, values in per_material.items()}
        for row, by_environment in environment_scores.rows.items():
            for environment, values in by_environment.items():
                for metric, numbers in values.items():
                    per_material.setdefault(row, {})[f"env_{_label(environment)}_{metric}"] = torch.from_numpy(numbers)
    metrics = sorted({key for values in per_material.values() for key in values})
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["material", "row"] + metrics)
    for row, values in per_material.items():
        for index, name in enumerate(names):
            writer.writerow([name, row] + [f"{float(values[m][index]):.6f}" if m in values else "" for m in metrics])
    write_bytes(out / "per_material.csv", buffer.getvalue().encode())

    columns = [("maps_normal", "normal"), ("maps_diffuse", "diffuse"), ("maps_roughness", "roughness"),
               ("maps_specular", "specular"), ("render_rmse", "render RMSE"), ("render_flip", "FLIP"),
               ("render_ssim", "SSIM"), ("render_lpips", "LPIPS"), ("seconds", "time [s]")]
    lines = ["| method | " + " | ".join(title for _, title in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for row, values in summary["rows"].items():
        cells = [f"{values[key]:.4f}" if isinstance(values.get(key), float) and key != "seconds"
                 else f"{values[key]:.1f}" if key == "seconds" and key in values else "-" for key, _ in columns]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines.append("| paper DeepBasis (122 scenes) | " + " | ".join(
        [f"{PAPER_DEEPBASIS[k]:.3f}" for k in ("normal", "diffuse", "roughness", "specular")] + ["-"] * 5) + " |")
    header = (f"Evaluation on {summary['n_materials']} materials of {summary['data']} ({summary['format']}), "
              f"light {summary['light']}, convention {summary['convention']}, seed {summary['seed']}. Map RMSE in the "
              "stored encoding; re-rendering under 30 random lights and views per material, clipped sRGB.\n\n")
    if "env" in summary:
        lines += ["", environment_table(summary)]
    write_bytes(out / "table.md", (header + "\n".join(lines) + "\n").encode())

    rows = list(summary["rows"])
    figure, axes = plt.subplots(1, 7, figsize=(23, 3.6))
    for axis, (key, title) in zip(axes, columns[:7]):
        values = [summary["rows"][r].get(key, float("nan")) for r in rows]
        axis.bar(range(len(rows)), values, color=[f"C{i}" for i in range(len(rows))])
        axis.set_xticks(range(len(rows)), [r.replace(" (", "\n(") for r in rows], fontsize=6, rotation=30)
        axis.set_title(title)
    figure.tight_layout()
    save_figure(figure, out / "bars.png")

    if environment_scores is not None:
        _environment_figures(out, summary, environment_scores, main_row, names)
    order = np.argsort(per_material[main_row]["render_rmse"].numpy())
    picks = list(order[:4]) + list(order[-4:])
    strips = []
    for index in picks:
        tiles = map_tiles(truth[index]) + map_tiles(predictions[main_row][index])
        strips.append(np.concatenate(tiles, axis=1))
    write_image(out / "gallery.png", np.clip(np.concatenate(strips, axis=0), 0, 1))


def _label(environment: str) -> str:
    from .environment import environment_label

    return environment_label(environment)


def environment_table(summary: dict) -> str:
    """The markdown table of the environment comparisons in ``summary['env']``."""
    protocol = summary["env_protocol"]
    lines = [f"Under environment light: path traced at {protocol['resolution']} px, {protocol['spp']} spp, views "
             f"{', '.join(f'{v:g}' for v in protocol['views_deg'])} deg from the normal, prediction and truth with "
             "the same seed; metrics over the pixels that see the sample (RMSE of clipped sRGB). The noise floor "
             "compares the truth with itself under another seed.", "",
             "| method | environment | RMSE | FLIP | SSIM |", "|---|---|---|---|---|"]
    for environment, entry in summary["env"].items():
        for row, values in entry["rows"].items():
            lines.append(f"| {row} | {environment} | {values['rmse']:.4f} | {values['flip']:.4f} | {values['ssim']:.4f} |")
        floor = entry["noise_floor"]
        lines.append(f"| noise floor | {environment} | {floor['rmse']:.4f} | {floor['flip']:.4f} | {floor['ssim']:.4f} |")
    rhos = {environment: entry.get("spearman_flash_vs_env") for environment, entry in summary["env"].items()}
    if any(value is not None for value in rhos.values()):
        lines += ["", "Spearman's rho between the materials' flash re-rendering RMSE and their RMSE under "
                  + "; ".join(f"{environment}: {value:.3f}" for environment, value in rhos.items() if value is not None)]
    return "\n".join(lines)


def _environment_figures(out: Path, summary: dict, scores, main_row: str, names: list[str]) -> None:
    """env_bars.png (RMSE, FLIP, SSIM per row and environment, the noise floor dashed) and
    env_gallery.png (truth | prediction | difference x 4 of the best and worst materials)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    environments = list(summary["env"])
    rows = list(next(iter(summary["env"].values()))["rows"])
    figure, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    width = 0.8 / len(rows)
    for axis, metric in zip(axes, ("rmse", "flip", "ssim")):
        for index, row in enumerate(rows):
            values = [summary["env"][e]["rows"][row][metric] for e in environments]
            axis.bar(np.arange(len(environments)) + index * width, values, width, label=row, color=f"C{index}")
        for position, environment in enumerate(environments):
            axis.hlines(summary["env"][environment]["noise_floor"][metric], position - 0.1, position + 0.9,
                        colors="k", linestyles="dashed", label="noise floor" if position == 0 else None)
        axis.set_xticks(np.arange(len(environments)) + 0.4 - width / 2, environments)
        axis.set_title(f"{metric.upper()} under environment light")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, out / "env_bars.png")

    keys = list(scores.rows[main_row])
    mean_rmse = np.mean([scores.rows[main_row][e]["rmse"] for e in keys], axis=0)
    order = np.argsort(mean_rmse)
    picks = list(dict.fromkeys(list(order[:3]) + list(order[-3:])))  # best three, worst three, each once
    strips = []
    for index in picks:
        tiles = []
        for environment in keys:
            truth, predicted = scores.images["truth"][environment][index], scores.images[main_row][environment][index]
            tiles += [truth, predicted, np.clip(np.abs(truth - predicted) * 4, 0, 1)]
        strips.append(np.concatenate(tiles, axis=1))
    write_image(out / "env_gallery.png", np.concatenate(strips, axis=0))


def lighting_figure(errors: dict[str, list[float]], robustness: list[dict], light: str, path: Path) -> Path:
    """lighting.png of ``evaluate --lighting``: the lighting search's angular errors [deg] per roughness
    group (a box each; empty groups left out) and the map and re-rendering RMSE against the flash
    offset angle (``robustness``: one {angle_deg, maps_rmse_mean, render_rmse} per angle)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    groups = [g for g in errors if errors[g]]
    left.boxplot([errors[g] for g in groups], tick_labels=[f"{g}\n(n={len(errors[g])})" for g in groups])
    left.set_ylabel("angular error of the found flash [deg]")
    left.set_title("lighting search by roughness group")
    right.plot([r["angle_deg"] for r in robustness], [r["maps_rmse_mean"] for r in robustness], "o-", label="maps RMSE (mean of 4)")
    right.plot([r["angle_deg"] for r in robustness], [r["render_rmse"] for r in robustness], "s-", label="re-rendering RMSE")
    right.set_xlabel("flash offset [deg]")
    right.set_title(f"robustness to the offset (light {light})")
    right.legend()
    figure.tight_layout()
    return save_figure(figure, path)
