"""Evaluation: map errors and re-rendering errors of predicted materials against ground truth.

``mideepbasis evaluate`` runs ``run_evaluation``: it writes ``summary.json``, ``per_material.csv``,
``table.md``, ``bars.png`` and ``gallery.png`` (the 4 best and 4 worst materials: true maps, then
predicted maps) and, with ``--lighting``, ``lighting.png``.

Protocol (the paper's): the input photo is re-rendered from the ground-truth maps under a flash
(centred, or a seeded hand-held offset per material), photographed as an 8-bit sRGB image, and
the method predicts the maps from it. Map RMSE is computed on the maps in their stored encoding
(the Deschaintre test maps are used as stored, so that is their in-memory value; normals as
(n + 1) / 2). The re-rendering error compares renders of the prediction and of the truth under
the same 30 random lights and viewpoints per material (seeded, identical for every method), on
clipped sRGB-encoded images.

Modules:

- ``metrics``: the metrics, each a plain function (map RMSE, re-rendering RMSE, SSIM, FLIP, LPIPS,
  the maps' detail above the network's band);
- ``protocol``: the photos, offsets, lights and views, and the evaluation materials;
- ``run``: ``EvaluationConfig`` and ``run_evaluation`` (the predictions and their scores);
- ``environment``: path-traced comparisons under environment light (``evaluate --environment``);
- ``real``: the real-photo protocol on calibrated scenes (``evaluate --data`` of such scenes);
- ``report``: the files (``write_evaluation``, the figures).

"""

from .metrics import (DETAIL_BAND, LPIPS, Scores, above_band, detail_ratio, flip, high_band_energy, light_error_deg,
                      map_rmse, rerender, rerender_rmse, score, ssim, ssim_map, summary_scores, trivial_baseline)
from .protocol import (PAPER_DEEPBASIS, RERENDER_COUNT, ROUGHNESS_GROUPS, EvaluationSet, evaluation_offsets,
                       flash_photos, load_evaluation_materials, load_evaluation_set, random_lights_and_views,
                       resize_maps)
from .run import EvaluationConfig, lighting_accuracy, run_evaluation

__all__ = [
    "EvaluationConfig", "run_evaluation", "lighting_accuracy",
    "DETAIL_BAND", "LPIPS", "Scores", "above_band", "detail_ratio", "flip", "high_band_energy", "light_error_deg",
    "map_rmse",
    "rerender", "rerender_rmse", "score", "ssim", "ssim_map", "summary_scores", "trivial_baseline",
    "PAPER_DEEPBASIS", "RERENDER_COUNT", "ROUGHNESS_GROUPS", "EvaluationSet", "evaluation_offsets", "flash_photos",
    "load_evaluation_materials", "load_evaluation_set", "random_lights_and_views", "resize_maps",
]
