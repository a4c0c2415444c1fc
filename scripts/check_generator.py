"""Generate materials of every procedural family and report failures (a new machine's first check).

    python3 scripts/check_generator.py [--count 20] [--size 128]
"""

import argparse
import sys
import time

from mideepbasis.data.procedural import FAMILIES, GeneratorConfig, generate

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--count", type=int, default=20, help="materials per family")
parser.add_argument("--size", type=int, default=128)
args = parser.parse_args()
failures, started = [], time.perf_counter()
for family in [*sorted(FAMILIES), None]:  # None: drawn from the seed, with mixes and weathering
    for seed in range(args.count):
        try:
            generate(seed, family=family, config=GeneratorConfig(size=args.size))
        except Exception as error:  # noqa: BLE001 - report every failure, go on
            failures.append(f"{family or 'any'} seed {seed}: {type(error).__name__}: {' '.join(str(error).split())[:200]}")
total = args.count * (len(FAMILIES) + 1)
print(f"{total} materials, {len(failures)} failed, {1e3 * (time.perf_counter() - started) / total:.1f} ms each")
print("\n".join(failures[:10]))
sys.exit(1 if failures else 0)
