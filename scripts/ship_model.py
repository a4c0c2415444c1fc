"""Make a training checkpoint the shipped model (mideepbasis/models/deepbasis_compact.safetensors).

    .venv/bin/python scripts/ship_model.py runs/RUN/best.safetensors [--half normal_unit] [--normal-unit-octaves 1 0.5]
    .venv/bin/python scripts/ship_model.py runs/RUN/model.safetensors --blend-with mideepbasis/models/deepbasis_compact.safetensors --blend-weight 0.5

The weights, configuration and training record are kept; the optimiser state of a resumable
checkpoint is not. ``--half`` stores the named parts (top-level modules) in float16, to keep the
package under issue 11's 20 MB; ``load_model`` casts them back to float32. The file is replaced
atomically, so the old weights are not kept beside it (MODEL.md records what they were).
``--normal-unit-octaves`` sets how the network runs its normal unit
(``NetworkConfig.normal_unit_octaves``), which needs no new weights.

``--blend-with`` ships the weights interpolated with another model's, ``w x checkpoint + (1 - w) x
other`` (``--blend-weight`` w): a fine-tune blended with the model it started from keeps much of
what the fine-tune learnt and much of what the start knew (Wortsman et al. 2022, "Robust
fine-tuning of zero-shot models"). Input channels the other model lacks count as zero weights
there, as a fine-tune widened from it starts (``train.trainer.widen_inputs``). ``--blend-parts``
blends only the named parts: a unit retrained on top of a blend keeps its new weights.
``--part-weight PART=W`` gives a part its own share.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from mideepbasis.model.checkpoint import SHIPPED_MODEL, load_model, read_checkpoint, save_checkpoint
from mideepbasis.train.trainer import widen_inputs

TARGET = Path(__file__).resolve().parents[1] / "mideepbasis" / "models" / SHIPPED_MODEL


def blend_weights(model: torch.nn.Module, other: torch.nn.Module, weight: float,
                  parts: tuple[str, ...] | None = None, part_weights: dict[str, float] | None = None) -> None:
    """Set ``model``'s weights to ``weight x model + (1 - weight) x other`` (in place), ``other``'s
    missing input channels as zeros; integer buffers stay ``model``'s, and so do the parts
    (top-level modules) not in ``parts`` when it is given. ``part_weights`` gives some parts
    their own ``weight``."""
    state, start = model.state_dict(), other.state_dict()
    if other.config.input_channels != model.config.input_channels:
        start = widen_inputs(start, state, other.config.input_channels)
    known = {name.split(".")[0] for name in state}
    part_weights = part_weights or {}
    for option, named in (("--blend-parts", parts or ()), ("--part-weight", part_weights)):
        unknown = sorted(set(named) - known)
        if unknown:
            raise SystemExit(f"ship_model: {option}: no part {unknown} in the network (its parts: {sorted(known)})")

    def share(name: str) -> float | None:  # the model's share of the blend, None: not blended
        part = name.split(".")[0]
        if parts is not None and part not in parts:
            return None
        return part_weights.get(part, weight)

    blended = {}
    for name, value in state.items():
        own = share(name) if value.is_floating_point() else None
        blended[name] = value if own is None else own * value + (1.0 - own) * start[name].to(value.dtype)
    model.load_state_dict(blended)


def part_weight(text: str) -> tuple[str, float]:
    """``PART=W`` for ``--part-weight``: W in [0, 1]."""
    part, _, value = text.partition("=")
    try:
        weight = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected PART=W, got {text!r}") from None
    if not part or not 0.0 <= weight <= 1.0:
        raise argparse.ArgumentTypeError(f"expected PART=W with W in [0, 1], got {text!r}")
    return part, weight


def shipped_metadata(document: dict, source: str, half: list[str]) -> dict:
    """What a shipped file keeps of its checkpoint's ``document``: the training record (with the
    file it came from and its float16 parts), the photo decoding and the field of view."""
    metadata = {key: value for key, value in document.items() if key in ("training", "photo_decoding", "fov_deg")}
    metadata["training"] = {**metadata.get("training", {}), "shipped_from": source, "float16_parts": half}
    return metadata


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--half", nargs="*", default=(), help="parts of the network stored in float16")
    parser.add_argument("--normal-unit-octaves", type=float, nargs="+", default=None,
                        help="weights of the normal unit's slope by octave (NetworkConfig.normal_unit_octaves)")
    parser.add_argument("--blend-with", type=Path, default=None,
                        help="a model (say, the one a fine-tune started from) whose weights are blended in")
    parser.add_argument("--blend-weight", type=float, default=0.5, help="the checkpoint's share of the blend")
    parser.add_argument("--blend-parts", nargs="+", default=None,
                        help="blend only these parts (top-level modules); the others stay the checkpoint's")
    parser.add_argument("--part-weight", type=part_weight, nargs="+", default=(), metavar="PART=W",
                        help="the checkpoint's share of the blend in these parts, instead of --blend-weight")
    parser.add_argument("-o", "--output", type=Path, default=TARGET)
    args = parser.parse_args()
    if args.part_weight and args.blend_with is None:
        parser.error("--part-weight needs --blend-with")
    if not 0.0 <= args.blend_weight <= 1.0:
        parser.error(f"--blend-weight must lie in [0, 1], got {args.blend_weight}")

    model = load_model(args.checkpoint)
    if args.blend_with is not None:
        blend_weights(model, load_model(args.blend_with), args.blend_weight,
                      None if args.blend_parts is None else tuple(args.blend_parts), dict(args.part_weight))
    document, _ = read_checkpoint(args.checkpoint)
    if args.normal_unit_octaves is not None:
        model.config = dataclasses.replace(model.config, normal_unit_octaves=tuple(args.normal_unit_octaves))
    for part in args.half:
        getattr(model, part).half()
    # Re-shipping the shipped file (to change how it runs) keeps the record of where it came from.
    source = (document.get("training", {}).get("shipped_from", str(args.checkpoint))
              if args.checkpoint.resolve() == TARGET else str(args.checkpoint))
    metadata = shipped_metadata(document, source, list(args.half))
    if args.blend_with is not None:
        metadata["training"]["blended_with"] = {"model": str(args.blend_with), "weight_of_shipped_from": args.blend_weight,
                                                "parts": args.blend_parts or "all",
                                                **({"part_weights": dict(args.part_weight)} if args.part_weight else {})}
    save_checkpoint(args.output, model, metadata=metadata)
    size = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({size:.1f} MiB)")


if __name__ == "__main__":
    main()
