"""A batch on a Dask distributed cluster (``mideepbasis.cluster``): the local batch's materials to
the bit, a corrupt photo one line, a worker killed mid-batch costing nothing."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mideepbasis import cli

distributed = pytest.importorskip("distributed", reason="dask[distributed] is not installed (pip install "
                                                        "'mideepbasis[cluster]')")

QUICK = ("--resolution", "64", "--refine-steps", "0", "--light", "0,0", "--symmetries", "1")


def photos(folder: Path, count: int) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    for index in range(count):
        pixels = np.random.default_rng(index).uniform(40, 200, (64, 64, 3)).astype(np.uint8)
        Image.fromarray(pixels).save(folder / f"p{index:02d}.png")
    return sorted(folder.iterdir())


def material_files(folder: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted(folder.iterdir())
            if path.suffix in (".png", ".exr") and path.stem in ("normal", "diffuse", "roughness", "specular", "height")}


def test_a_cluster_batch_writes_the_local_batchs_materials_and_a_bad_photo_is_one_line(tmp_path, tiny_checkpoint,
                                                                                      capsys):
    photos(tmp_path / "in", 3)
    (tmp_path / "in" / "broken.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    common = ["capture", str(tmp_path / "in"), "--model", str(tiny_checkpoint), *QUICK]
    assert cli.main(common + ["-o", str(tmp_path / "local"), "--workers", "2"]) == 1
    capsys.readouterr()
    assert cli.main(common + ["-o", str(tmp_path / "cluster"), "--cluster", "local:2"]) == 1
    printed = capsys.readouterr()
    lines = [line for line in (printed.out + printed.err).splitlines() if "broken.jpg" in line]
    assert len(lines) == 1 and "skipped" in lines[0] and "captured 3 of 4 photos" in printed.out
    for name in ("p00", "p01", "p02"):
        assert material_files(tmp_path / "cluster" / name) == material_files(tmp_path / "local" / name), name
    assert not (tmp_path / "cluster" / "broken").exists()


def test_a_worker_killed_mid_batch_leaves_every_photo_captured_once(tmp_path, tiny_checkpoint):
    from distributed import Client, LocalCluster

    from mideepbasis.batch import SaveOptions
    from mideepbasis.capturing import CaptureConfig, RefineConfig
    from mideepbasis.cluster import cluster_batch
    from mideepbasis.outputs import MANIFEST

    shots = photos(tmp_path / "in", 10)
    config = CaptureConfig(resolution=64, refine=RefineConfig(steps=0), light=(0.0, 0.0), symmetries=1)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        items = cluster_batch(shots, tmp_path / "out", cluster.scheduler_address, tiny_checkpoint, config,
                              SaveOptions())
        seen = [next(items)]
        victim = next(iter(client.run(os.getpid).values()))
        os.kill(victim, signal.SIGKILL)  # mid-batch: its photos go to the other worker or its restart
        seen += list(items)
    assert sorted(item.photo.name for item in seen) == [shot.name for shot in shots]  # each once
    assert all(item.error is None for item in seen), [item.error for item in seen if item.error]
    tokens = set()
    for shot in shots:
        folder = tmp_path / "out" / shot.stem
        manifest = json.loads((folder / MANIFEST).read_text())
        present = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != MANIFEST)
        assert present == sorted(manifest["entries"]), shot  # whole
        tokens.add(manifest["batch"])
    assert len(tokens) == 1  # all written by this batch
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]  # no leftovers
