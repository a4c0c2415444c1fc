"""Training DeepBasisNet: L = L_sup + 0.05 L_vc on synthesised flash photos, resumable, DDP-ready.

    mideepbasis train --preset compact --data procedural --steps 20000 --batch 8 --out runs/compact
    torchrun --nproc_per_node 2 -m mideepbasis.cli train ...          # several processes, no change

Every step draws a batch of materials (procedural, or folders of materials), synthesises their
photos and the photos of their variations M + xi under hand-held flashes (``data.synth``),
predicts both and minimises

    L_sup = |maps(M) - M|_1                                  (signed space, as the paper)
    L_vc  = |xi(bases(M)) - bases(M + xi)|_1 + |maps(M + xi) - (M + xi)|_1

with Adam and a cosine learning-rate decay. Material number i of the run is always the same
material and the synthesis generator's state is saved, so ``--resume`` continues exactly where a
killed run stopped. Rank 0 writes ``OUT/train.jsonl`` (losses, learning rate, speed),
``OUT/loss.png``, validation sheets ``OUT/validation/step_XXXXXXX.png``, ``OUT/checkpoint.safetensors``
every few minutes (atomically) and ``OUT/model.safetensors`` at the end.

Modules:

- ``config``: ``TrainConfig``, the run's settings, and the tables that go with them;
- ``data``: the training materials by number, their augmentation, the batches of numbers each
  step takes, and the photographed pools of a unit trained alone;
- ``losses``: the losses, the re-rendering loss's lights and views, the learning-rate schedule;
- ``trainer``: ``Trainer`` (the loop, its checkpoints and validations) and ``train``.

The metrics that validation logs live in ``evaluation.metrics``.
"""

from __future__ import annotations

from .config import LOCAL_UNIT_FIELDS, RESUMABLE_CHANGES, TRAINABLE_PARTS, TrainConfig
from .data import (LocalUnitBatch, LocalUnitPool, NormalUnitPool, PhotographedPool, StepBatchSampler, TrainingMaterials,
                   augment)
from .losses import (HIGHLIGHT_PEAK_QUANTILE, channel_weights, global_blend_loss, highlight_weights,
                     learning_rate_factor, normal_unit_loss, normals_over_flat, rendering_loss, sample_render_geometry,
                     saturation_penalty, specular_colour_loss, specular_lobe, supervised_loss,
                     variation_consistency_loss, vary_signed)
from .trainer import VALIDATION_CHUNK, VALIDATION_SEED, Trainer, TrainingDiverged, train, widen_inputs

__all__ = [
    "TrainConfig", "LOCAL_UNIT_FIELDS", "RESUMABLE_CHANGES", "TRAINABLE_PARTS",
    "TrainingMaterials", "augment", "StepBatchSampler", "PhotographedPool", "NormalUnitPool", "LocalUnitPool",
    "LocalUnitBatch",
    "supervised_loss", "variation_consistency_loss", "vary_signed", "channel_weights", "saturation_penalty",
    "rendering_loss", "sample_render_geometry", "learning_rate_factor", "normal_unit_loss", "normals_over_flat",
    "highlight_weights", "specular_lobe", "global_blend_loss", "specular_colour_loss",
    "HIGHLIGHT_PEAK_QUANTILE",
    "Trainer", "TrainingDiverged", "train", "widen_inputs", "VALIDATION_SEED", "VALIDATION_CHUNK",
]
