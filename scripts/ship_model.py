"""Make a training checkpoint the shipped model (mideepbasis/models/deepbasis_compact.safetensors).

    .venv/bin/python scripts/ship_model.py runs/RUN/best.safetensors [--half normal_unit] [--normal-unit-octaves 1 0.5]

The weights, configuration and training record are kept; the optimiser state of a resumable
checkpoint is not. ``--half`` stores the named parts (top-level modules) in float16, to keep the
package under issue 11's 20 MB; ``load_model`` casts them back to float32. The file is replaced
atomically, so the old weights are not kept beside it (MODEL.md records what they were).
``--normal-unit-octaves`` sets how the network runs its normal unit
(``NetworkConfig.normal_unit_octaves``), which needs no new weights.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from mideepbasis.model.checkpoint import SHIPPED_MODEL, load_model, read_checkpoint, save_checkpoint

TARGET = Path(__file__).resolve().parents[1] / "mideepbasis" / "models" / SHIPPED_MODEL


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--half", nargs="*", default=(), help="parts of the network stored in float16")
    parser.add_argument("--normal-unit-octaves", type=float, nargs="+", default=None,
                        help="weights of the normal unit's slope by octave (NetworkConfig.normal_unit_octaves)")
    parser.add_argument("-o", "--output", type=Path, default=TARGET)
    args = parser.parse_args()

    model = load_model(args.checkpoint)
    document, _ = read_checkpoint(args.checkpoint)
    if args.normal_unit_octaves is not None:
        model.config = dataclasses.replace(model.config, normal_unit_octaves=tuple(args.normal_unit_octaves))
    for part in args.half:
        getattr(model, part).half()
    metadata = {key: value for key, value in document.items() if key in ("training", "photo_decoding", "fov_deg")}
    training = metadata.get("training", {})
    # Re-shipping the shipped file (to change how it runs) keeps the record of where it came from.
    source = training.get("shipped_from", str(args.checkpoint)) if args.checkpoint.resolve() == TARGET else str(args.checkpoint)
    metadata["training"] = {**training, "shipped_from": source, "float16_parts": list(args.half)}
    save_checkpoint(args.output, model, metadata=metadata)
    size = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({size:.1f} MiB)")


if __name__ == "__main__":
    main()
