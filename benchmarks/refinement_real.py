"""The refinement's levers under the real-photo protocol: card-blue and the held-out phone scenes side by side.

    .venv/bin/mideepbasis data scenes --n 24 -o runs/phone_scenes     # the validation set, once
    .venv/bin/python benchmarks/refinement_real.py [--model CKPT] [--variants default,prior0.1,...]

For each variant of ``RefineConfig`` (``VARIANTS``) or of the capture around it
(``CAPTURE_VARIANTS``) it runs ``evaluate``'s real protocol (``evaluation.real``) on the
calibrated real scenes (every photo in turn as the input, and photo 00 alone, the default
protocol) and on the validation scenes (photo 00 as the input), and reports the re-rendering
RMSE of the refined capture beside the unrefined one. A lever is good only where both sets
agree. Writes the entry ``real`` of results/refinement.json.
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

from common import RESULTS, SHARED_TEST, write_section

from mideepbasis.capturing import CaptureConfig
from mideepbasis.evaluation import EvaluationConfig
from mideepbasis.evaluation.real import CAPTURE_ROW, UNREFINED_ROW, run_real_evaluation

#: The variants: RefineConfig fields changed from capture's default.
VARIANTS = {
    "default": {},
    "constant": {"steps": 125, "lr_schedule": "constant"},
    "clamped": {"unclamped_moves": False},
    "clamped_achromatic": {"unclamped_moves": False, "achromatic_specular": True},
    "skip_clipped": {"skip_clipped": True},
    "achromatic": {"achromatic_specular": True},
    "prior0.05": {"prior": 0.05},
    "prior0.2": {"prior": 0.2},
    "prior0.5": {"prior": 0.5},
    "prior2": {"prior": 2.0},
    "prior5": {"prior": 5.0},
    "prior10": {"prior": 10.0},
    "steps40": {"steps": 40},
    "combined": {"skip_clipped": True, "achromatic_specular": True, "prior": 0.05},
    "encoded": {"encoded_loss": True},
    "encoded_achromatic": {"encoded_loss": True, "achromatic_specular": True},
    "encoded_prior0.05": {"encoded_loss": True, "prior": 0.05},
    "diffuse_only": {"moving_maps": ("diffuse",)},
    "diffuse_roughness": {"moving_maps": ("diffuse", "roughness")},
    "diffuse_specular": {"moving_maps": ("diffuse", "specular")},
    "resolution128": {"resolution": 128},
    "steps250": {"steps": 250},
    "normals": {"normals": True},
}

#: Variants of the capture around the refinement: ``EvaluationConfig`` fields shared with capture
#: (``evaluation.run.SHARED_CAPTURE_FIELDS``) changed from capture's default, the refinement's own.
CAPTURE_VARIANTS = {
    "lobe1": {"lobe_variation": 1.0},
    "lobe0.75": {"lobe_variation": 0.75},
    "lobe0.25": {"lobe_variation": 0.25},
    "lobe0": {"lobe_variation": 0.0},
    "lobe1_encoded": {"lobe_variation": 1.0, "refine": {"encoded_loss": True}},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--real", type=Path, default=SHARED_TEST.parent / "real-calibrated")
    parser.add_argument("--validation", type=Path, default=Path("runs/phone_scenes"))
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="comma-separated names of VARIANTS and CAPTURE_VARIANTS")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "refinement.json")
    args = parser.parse_args()
    default = CaptureConfig().refine
    rows = {}
    for name in args.variants.split(","):
        if name not in VARIANTS and name not in CAPTURE_VARIANTS:
            raise SystemExit(f"unknown variant {name!r}; known: {', '.join([*VARIANTS, *CAPTURE_VARIANTS])}")
        capture_fields = dict(CAPTURE_VARIANTS.get(name, {}))
        refine_fields = {**VARIANTS.get(name, {}), **capture_fields.pop("refine", {})}
        refine = replace(default, **refine_fields)
        rows[name] = {"refine": refine_fields, "capture": capture_fields}
        for label, data, inputs in (("real", args.real, "all"), ("real_photo00", args.real, 0),
                                    ("validation", args.validation, 0)):
            with tempfile.TemporaryDirectory() as folder:
                config = EvaluationConfig(data=str(data), format="calibrated", input_photo=inputs, model=args.model,
                                          refine=refine, **capture_fields)
                summary = run_real_evaluation(config, Path(folder), progress=False)
            figures = summary["rows"]
            rows[name][label] = {"refined": figures[CAPTURE_ROW]["rmse"], "unrefined": figures[UNREFINED_ROW]["rmse"],
                                 "refined_least_squares": figures[CAPTURE_ROW]["rmse_least_squares"],
                                 "per_scene": {scene: values[CAPTURE_ROW]["rmse"]
                                               for scene, values in summary["scenes"].items()}}
        real, photo00, validation = rows[name]["real"], rows[name]["real_photo00"], rows[name]["validation"]
        print(f"{name:14s} real {real['refined']:.4f} (unrefined {real['unrefined']:.4f}, least squares "
              f"{real['refined_least_squares']:.4f}; photo 00 {photo00['refined']:.4f}, unrefined "
              f"{photo00['unrefined']:.4f})   validation {validation['refined']:.4f} "
              f"(unrefined {validation['unrefined']:.4f})", flush=True)
    write_section(args.output, "real", "refinement_real", {"model": args.model or "shipped", "rows": rows})


if __name__ == "__main__":
    main()
