"""Figures people look at: loss curves and validation sheets (PNG, written atomically)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .imageio import linear_to_srgb, write_image


def _save_figure(figure, path: Path) -> Path:
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp{path.suffix}")
    figure.savefig(temporary, dpi=100)
    plt.close(figure)
    temporary.replace(path)
    return path


def plot_training_log(log_path: Path, output: Path) -> Path | None:
    """Loss curves (total, supervised, variation consistency) and validation RMSE from a train.jsonl."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    records = [json.loads(line) for line in Path(log_path).read_text().splitlines() if line.strip()]
    losses = [r for r in records if "loss" in r]
    validation = [r for r in records if "validation_rmse" in r]
    if not losses:
        return None
    figure, axes = plt.subplots(1, 2 if validation else 1, figsize=(12 if validation else 6, 4), squeeze=False)
    steps = [r["step"] for r in losses]
    for key, label in (("loss", "total"), ("l_sup", "supervised L1"), ("l_vc", "variation consistency")):
        axes[0, 0].plot(steps, [r[key] for r in losses], label=label)
    axes[0, 0].set_xlabel("step")
    axes[0, 0].set_yscale("log")
    axes[0, 0].set_title("training losses")
    axes[0, 0].legend()
    if validation:
        for name in validation[0]["validation_rmse"]:
            axes[0, 1].plot([r["step"] for r in validation], [r["validation_rmse"][name] for r in validation], label=name)
        axes[0, 1].set_xlabel("step")
        axes[0, 1].set_title("validation map RMSE (held-out procedural)")
        axes[0, 1].legend()
    figure.tight_layout()
    return _save_figure(figure, output)


def map_tiles(maps: torch.Tensor) -> list[np.ndarray]:
    """(10, H, W) maps as four (H, W, 3) sRGB-encoded tiles: normal, diffuse, roughness, specular."""
    hwc = maps.detach().cpu().permute(1, 2, 0).numpy()
    return [(hwc[..., 0:3] + 1) / 2, linear_to_srgb(np.clip(hwc[..., 3:6], 0, 1)),
            np.repeat(hwc[..., 6:7], 3, axis=2), linear_to_srgb(np.clip(hwc[..., 7:10], 0, 1))]


def validation_sheet(photos: torch.Tensor, predicted: torch.Tensor, truth: torch.Tensor, output: Path) -> Path:
    """Per row: the input photo, then predicted and true maps side by side (normal, diffuse, roughness, specular)."""
    rows = []
    for photo, pred, true in zip(photos, predicted, truth):
        tiles = [linear_to_srgb(photo.detach().cpu().permute(1, 2, 0).numpy().clip(0, 1))]
        for p, t in zip(map_tiles(pred), map_tiles(true)):
            tiles += [p, t]
        rows.append(np.concatenate(tiles, axis=1))
    return write_image(output, np.clip(np.concatenate(rows, axis=0), 0, 1))
