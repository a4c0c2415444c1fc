"""How much of the normal can a flash photo tell? Probes trained for the normal alone.

    .venv/bin/python benchmarks/normal_probe.py [--probe linear|unit] [--minutes 40] [--loss l2|l1]

Both probes read ``model.inputs.relief_inputs`` (the photo's shading beside the flash direction)
and predict the normal's x and y; nothing else of a material is predicted.

- ``linear``: ridge regression per pixel on a quadratic expansion of multi-scale shading
  features and the flash direction (seconds). What a local, nearly linear reading can get.
- ``unit``: the normal unit's NAFNet (``NetworkConfig.normal_unit_width`` 16), trained alone with
  Adam 1e-3 on random 64 px crops (batch 16) of a fixed pool of 512 procedural materials rendered
  at 128 px, for ``--minutes`` of wall time.

Reported: normal RMSE (unit vectors, mean over the three components) on the 32 held-out
validation materials of ``train`` beside the flat normal's, and on the shared test set (in its
stored encoding, the photos of ``evaluate``'s default protocol, the probe run at 128 px and
its slopes upsampled) beside the flat normal's. The shared set is only measured, never trained
on. Writes benchmarks/results/normal_probe_<probe>.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
import torch.nn.functional as F
from common import RESULTS, SHARED_TEST, write_report

from mideepbasis.data.procedural import GeneratorConfig, generate
from mideepbasis.data.synth import SynthesisConfig, synthesize
from mideepbasis.model.inputs import relief_inputs
from mideepbasis.model.network import normal_unit
from mideepbasis.resampling import gaussian_blur
from mideepbasis.train import VALIDATION_SEED

SIZE, CROP, BATCH, POOL = 128, 64, 16, 512
#: First seed of the probe's training pool (far from the validation seeds, 1e9 + i).
POOL_SEED = 7000


def photographed(seeds, generator_seed: int, validation: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(relief inputs (B, 7, 128, 128), true normals (B, 3, 128, 128)) of procedural materials."""
    # The validation set is made as train's is (relief by a factor, not scaled to a drawn tilt).
    config = GeneratorConfig(size=SIZE, relief_tilt_deg=None) if validation else GeneratorConfig(size=SIZE)
    maps = torch.stack([generate(seed, config=config).to_tensor() for seed in seeds])
    batch = synthesize(maps, torch.Generator().manual_seed(generator_seed), SynthesisConfig())
    return relief_inputs(batch.photos, batch.lights), maps[:, :3]


def unit_normals(xy: torch.Tensor) -> torch.Tensor:
    """Normals (B, 3, H, W) of predicted x and y (B, 2, H, W)."""
    xy = xy.clamp(-0.95, 0.95)
    normal = torch.cat([xy, (1 - (xy**2).sum(1, keepdim=True)).clamp(min=1e-3).sqrt()], 1)
    return normal / normal.norm(dim=1, keepdim=True)


def flat_like(normals: torch.Tensor) -> torch.Tensor:
    flat = torch.zeros_like(normals)
    flat[:, 2] = 1.0
    return flat


def rmse(predicted: torch.Tensor, truth: torch.Tensor) -> float:
    return float(((predicted - truth) ** 2).mean().sqrt())


def quadratic_features(relief: torch.Tensor) -> torch.Tensor:
    """(B, F, H, W): 1, the flash direction, shading high-passes and gradients at four scales, and
    every product of two of them."""
    shading = relief[:, 3:4] / 0.3
    base = [relief[:, 5:6] / 3, relief[:, 6:7] / 3]
    for sigma in (1.0, 2.0, 4.0, 8.0):
        blurred = gaussian_blur(shading, sigma)
        gx = (torch.roll(blurred, -1, 3) - torch.roll(blurred, 1, 3)) / 2
        gy = (torch.roll(blurred, 1, 2) - torch.roll(blurred, -1, 2)) / 2
        base += [shading - gaussian_blur(shading, 2 * sigma), gx * sigma, gy * sigma]
    base = torch.cat(base, 1)
    products = [base[:, i:i + 1] * base[:, j:j + 1] for i in range(base.shape[1]) for j in range(i, base.shape[1])]
    return torch.cat([torch.ones_like(base[:, :1]), base, *products], 1)


def linear_probe(train_x, train_n):
    """A predictor of normals from relief inputs: ridge regression on ``quadratic_features``."""
    def rows(x):
        features = quadratic_features(x)
        return features.permute(0, 2, 3, 1).reshape(-1, features.shape[1]).double()

    features = rows(train_x)[::7]
    targets = train_n[:, :2].permute(0, 2, 3, 1).reshape(-1, 2).double()[::7]
    mean, scale = features.mean(0), features.std(0).clamp(min=1e-8)
    mean[0], scale[0] = 0.0, 1.0
    normalised = (features - mean) / scale
    gram = normalised.T @ normalised + 1e-4 * len(normalised) * torch.eye(normalised.shape[1], dtype=torch.float64)
    coefficients = torch.linalg.solve(gram, normalised.T @ targets)

    def predict(x):
        xy = ((rows(x) - mean) / scale) @ coefficients
        return unit_normals(xy.float().reshape(x.shape[0], *x.shape[-2:], 2).permute(0, 3, 1, 2))

    return predict


def unit_probe(train_x, train_n, valid_x, valid_n, minutes: float, loss_name: str, log: list):
    """A predictor of normals from relief inputs: the normal unit's NAFNet trained alone."""
    torch.manual_seed(0)
    network = normal_unit(16)
    optimiser = torch.optim.AdamW(network.parameters(), 1e-3, weight_decay=1e-4)
    generator = torch.Generator().manual_seed(0)

    def predict(x):
        return unit_normals(torch.tanh(network(x)))

    step, started = 0, time.monotonic()
    while time.monotonic() - started < minutes * 60:
        index = torch.randint(0, len(train_x), (BATCH,), generator=generator)
        i, j = torch.randint(0, SIZE - CROP + 1, (2,), generator=generator).tolist()
        x, truth = train_x[index, :, i:i + CROP, j:j + CROP], train_n[index, :, i:i + CROP, j:j + CROP]
        for group in optimiser.param_groups:
            group["lr"] = 1e-3 * min(1.0, (step + 1) / 100)
        difference = predict(x) - truth
        loss = (difference**2).mean() if loss_name == "l2" else difference.abs().mean()
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(network.parameters(), 1.0)
        optimiser.step()
        step += 1
        if step % 200 == 0:
            network.eval()
            with torch.no_grad():
                value = rmse(torch.cat([predict(valid_x[k:k + 8]) for k in range(0, len(valid_x), 8)]), valid_n)
            network.train()
            log.append({"step": step, "seconds": round(time.monotonic() - started), "validation_rmse": value})
            print(f"step {step}: validation {value:.4f} (flat {rmse(flat_like(valid_n), valid_n):.4f})", flush=True)
    network.eval()
    return predict


def shared_set_rmse(predict) -> dict | None:
    """Per-material mean normal RMSE on the shared set (stored encoding): the probe and flat."""
    if not SHARED_TEST.is_dir():
        print(f"{SHARED_TEST} is absent: no shared-set figures")
        return None
    from mideepbasis.evaluation.protocol import evaluation_offsets, flash_photos, load_evaluation_materials

    materials = load_evaluation_materials(SHARED_TEST, "deschaintre5")
    photos, lights = flash_photos(materials.maps, evaluation_offsets(len(materials.maps), 0, 45.0))
    truth = materials.stored[:, :3] * 0.5 + 0.5
    predicted = []
    with torch.no_grad():
        for k in range(0, len(photos), 8):
            small = F.interpolate(photos[k:k + 8], size=(SIZE, SIZE), mode="area")
            normals = predict(relief_inputs(small, lights[k:k + 8]))
            xy = F.interpolate(normals[:, :2], size=truth.shape[-2:], mode="bilinear", align_corners=False)
            predicted.append(unit_normals(xy))
    predicted = torch.cat(predicted) * 0.5 + 0.5
    flat = flat_like(predicted) * 0.5 + 0.5
    probe = ((predicted - truth) ** 2).mean(dim=(1, 2, 3)).sqrt()
    baseline = ((flat - truth) ** 2).mean(dim=(1, 2, 3)).sqrt()
    return {"probe": float(probe.mean()), "flat": float(baseline.mean()),
            "fraction_better": float((probe < baseline).float().mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--probe", choices=("linear", "unit"), default="unit")
    parser.add_argument("--minutes", type=float, default=40.0, help="training wall time of the unit probe")
    parser.add_argument("--loss", choices=("l2", "l1"), default="l2", help="loss of the unit probe")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("-o", "--output", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    chunks = [photographed(range(POOL_SEED + c, POOL_SEED + c + 32), c) for c in range(0, POOL, 32)]
    train_x, train_n = torch.cat([c[0] for c in chunks]), torch.cat([c[1] for c in chunks])
    valid_x, valid_n = photographed([VALIDATION_SEED + i for i in range(32)], 12345, validation=True)
    log = []
    if args.probe == "linear":
        predict = linear_probe(train_x, train_n)
    else:
        predict = unit_probe(train_x, train_n, valid_x, valid_n, args.minutes, args.loss, log)
    with torch.no_grad():
        validation = rmse(torch.cat([predict(valid_x[k:k + 8]) for k in range(0, len(valid_x), 8)]), valid_n)
    flat = rmse(flat_like(valid_n), valid_n)
    print(f"validation: probe {validation:.4f}, flat {flat:.4f} ({validation / flat - 1:+.1%})")
    shared = shared_set_rmse(predict)
    if shared:
        print(f"shared set: probe {shared['probe']:.4f}, flat {shared['flat']:.4f} "
              f"({shared['probe'] / shared['flat'] - 1:+.1%}), better on {shared['fraction_better']:.0%} of materials")
    output = args.output or RESULTS / f"normal_probe_{args.probe}.json"
    write_report(output, "normal_probe", {"probe": args.probe, "minutes": args.minutes, "loss": args.loss,
                                          "validation": {"probe": validation, "flat": flat}, "shared": shared,
                                          "curve": log})


if __name__ == "__main__":
    main()
