"""Shared pytest set-up: the `slow` marker and the path of the shared evaluation data."""

from __future__ import annotations

from pathlib import Path

import pytest

#: The read-only evaluation data beside the repository (never copied into it).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture(scope="package")
def shared_data() -> Path:
    """../shared/data, or a skip with a message where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared evaluation data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="package")
def evaluation_dataset(tmp_path_factory):
    """A folder of three readable 32 px materials and one corrupt one (a map of the wrong size),
    and an untrained tiny checkpoint: (folder, checkpoint path)."""
    import numpy as np
    import torch

    from mideepbasis.imageio import write_image
    from mideepbasis.material import Material
    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    folder = tmp_path_factory.mktemp("materials")
    generator = torch.Generator().manual_seed(0)
    for index in range(3):
        normal = torch.nn.functional.normalize(torch.randn(3, 32, 32, generator=generator) * 0.2
                                               + torch.tensor([0, 0, 1.0]).view(3, 1, 1), dim=0)
        Material(normal, torch.rand(3, 32, 32, generator=generator), torch.rand(1, 32, 32, generator=generator),
                 torch.full((3, 32, 32), 0.04)).save(folder / f"m{index}")
    broken = folder / "m9"
    Material.constant(32, 32).save(broken)
    write_image(broken / "diffuse.png", np.full((8, 8, 3), 0.5, np.float32))  # wrong size: skipped
    torch.manual_seed(0)
    model = save_checkpoint(folder.parent / "tiny.safetensors", DeepBasisNet(preset("tiny")).eval())
    return folder, model


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """An untrained checkpoint of the tiny preset: quick captures whose maps are nonsense."""
    import torch

    from mideepbasis.model.checkpoint import save_checkpoint
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("model") / "tiny.safetensors", DeepBasisNet(preset("tiny")).eval())
