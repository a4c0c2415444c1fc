"""Network size and speed: parameters and forward time of each preset, training steps per second.

    .venv/bin/python benchmarks/model.py [--sizes 256 1024] [--train-steps 4] [--forward-only] [-o benchmarks/results/model.json]

Forward times are warm medians (inference, no gradients, the error-map render included) on this
machine's cores; training speed is measured with the real loop (synthesis, both passes of the
variation-consistency loss, backward, Adam) for the compact preset at the given batch.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import mideepbasis  # noqa: F401  (sets the OpenMP spin before torch loads)
import torch
from common import RESULTS, write_report

from mideepbasis import geometry
from mideepbasis.model.network import DeepBasisNet, count_parameters, preset

TARGETS = {"compact_parameters": 4_000_000, "compact_forward_256_ms": 150.0}


#: Networks whose size and forward time are measured: name -> (preset, overrides).
NETWORKS = {"compact": ("compact", {}), "compact_normal_unit16": ("compact", {"normal_unit_width": 16}),
            "paper": ("paper", {})}


def forward_ms(name: str, size: int, repeats: int, **overrides) -> float:
    torch.manual_seed(0)
    model = DeepBasisNet(preset(name, **overrides)).eval()
    inputs = torch.rand(1, 9, size, size) * 2 - 1
    lights = geometry.light_positions(torch.zeros(1, 2))
    runs = []
    with torch.no_grad():
        model(inputs, lights)
        for _ in range(repeats):
            start = time.perf_counter()
            model(inputs, lights)
            runs.append(1e3 * (time.perf_counter() - start))
    return round(statistics.median(runs), 1)


#: Training settings whose speed is measured: name -> TrainConfig overrides (batch and size apart).
TRAINING_SETTINGS = {
    "fp32": {},
    "bf16": {"bf16": True},
    "bf16_render_loss": {"bf16": True, "render_weight": 1.0},
}


def training_steps_per_second(size: int, batch: int, steps: int, workers: int = 2, **overrides) -> float:
    """Steps per second of the real loop (materials from the workers, synthesis, both VC passes,
    backward, Adam) after one warm-up step."""
    from mideepbasis.train import TrainConfig, Trainer

    with tempfile.TemporaryDirectory() as folder:
        config = TrainConfig(out=folder, preset="compact", steps=steps + 1, batch=batch, size=size, workers=workers,
                             validate_every=0, checkpoint_minutes=1e9, **overrides)
        trainer = Trainer(config, progress=False)
        iterator = iter(trainer.loader())
        trainer.train_step(next(iterator))  # warm-up: kernels compiled, workers started
        start = time.perf_counter()
        for _ in range(steps):
            trainer.train_step(next(iterator))
        return round(steps / (time.perf_counter() - start), 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--train-steps", type=int, default=4)
    parser.add_argument("--train-batch", type=int, default=8)
    parser.add_argument("--forward-only", action="store_true", help="sizes and forward times only")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "model.json")
    args = parser.parse_args()

    presets = {}
    for name, (base, overrides) in NETWORKS.items():
        presets[name] = {"parameters": count_parameters(DeepBasisNet(preset(base, **overrides))),
                         "forward_ms": {str(size): forward_ms(base, size, args.repeats if size <= 256 else 2, **overrides)
                                        for size in args.sizes if size % preset(base).stride == 0}}
        print(name, presets[name])
    if args.forward_only:
        write_report(args.output, "model", {"targets": TARGETS, "presets": presets})
        return
    training = {f"compact_{size}px_batch{args.train_batch}": training_steps_per_second(size, args.train_batch, args.train_steps)
                for size in (128, 256)}
    settings = {}
    for name, overrides in TRAINING_SETTINGS.items():
        rate = training_steps_per_second(128, args.train_batch, args.train_steps, **overrides)
        settings[name] = {"steps_per_second": rate, "materials_per_second": round(rate * args.train_batch, 3)}
        print(f"128 px, batch {args.train_batch}, {name}: {rate} steps/s")
    training["settings_128px"] = settings
    print("training steps/s:", training)
    write_report(args.output, "model", {"targets": TARGETS, "presets": presets, "training_steps_per_second": training})


if __name__ == "__main__":
    main()
