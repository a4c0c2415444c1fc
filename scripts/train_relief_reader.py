"""Train the relief reader (``mideepbasis.model.relief_reader``) on procedural materials photographed
at 1024 px, on the CPU, resumable:

    nice -n 19 .venv/bin/python scripts/train_relief_reader.py --out runs/relief_reader --max-minutes 120
    nice -n 19 .venv/bin/python scripts/train_relief_reader.py --out runs/relief_reader --resume --max-minutes 120
    nice -n 19 .venv/bin/python scripts/train_relief_reader.py --out runs/relief_unit --init-from-unit \
        --render-weight 4 --max-minutes 120      # from the shipped normal unit, with the re-rendering loss

Every option is a field of ``train.relief_reader.ReliefTrainingConfig``; on ``--resume`` the run's
stored material settings (size, band, crop, pool, stream seed, width, the unit's start) are kept. What it writes under
``--out``: ``checkpoint.safetensors`` (weights and Adam's state), ``best.safetensors`` (the weights
of the least validation error), ``log.jsonl`` and ``curve.png``.
"""

from __future__ import annotations

import argparse
import sys

from mideepbasis.configs import add_config_arguments, config_from_arguments
from mideepbasis.errors import InputError
from mideepbasis.train.relief_reader import ReliefTrainingConfig, train_reader


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Train the relief reader on procedural materials at 1024 px.")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    add_config_arguments(parser, ReliefTrainingConfig)
    args = parser.parse_args(argv)
    args.command = "train_relief_reader"
    try:
        config = config_from_arguments(ReliefTrainingConfig, args)
        path = train_reader(config, resume=args.resume)
    except InputError as error:
        print(f"train_relief_reader: error: {error}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
