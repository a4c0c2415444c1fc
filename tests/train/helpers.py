"""Small training runs the tests of ``mideepbasis.train`` share."""

from __future__ import annotations

import torch

from mideepbasis.train import TrainConfig


def tiny_config(tmp_path, **overrides):
    """A run of the tiny network on 32 px materials, four steps of two, written to ``tmp_path / "run"``."""
    values = dict(out=str(tmp_path / "run"), preset="tiny", steps=4, batch=2, size=32, workers=0, validate_every=0,
                  log_every=1, checkpoint_minutes=1e9, lr=3e-3, local_lr=3e-3)
    values.update(overrides)
    return TrainConfig(**values)


def procedural_maps(count: int = 2) -> torch.Tensor:
    """(count, 10, 32, 32) procedural materials of seeds 0, 1, ..."""
    from mideepbasis.data.procedural import GeneratorConfig, generate

    return torch.stack([generate(seed, config=GeneratorConfig(size=32)).to_tensor() for seed in range(count)])


def pool_config(tmp_path, **overrides):
    """A run of the normal unit alone on a pool of three materials (``TrainConfig.normal_pool``)."""
    values = dict(network={"normal_unit_width": 4}, train_only=("normal_unit",), vc_weight=0.0, normal_pool=3,
                  normal_crop=16)
    return tiny_config(tmp_path, **{**values, **overrides})


def local_pool_config(tmp_path, **overrides):
    """A run of the local unit alone on a pool of three materials (``TrainConfig.local_pool``)."""
    values = dict(network={"normal_unit_width": 4}, train_only=("local_unit",), vc_weight=0.0, local_pool=3)
    return tiny_config(tmp_path, **{**values, **overrides})


def network_with_a_working_normal_unit():
    """A tiny network with a normal unit of width 4 whose residual scales are away from their zero
    start, so that every block computes something (seeded)."""
    from mideepbasis.model.network import DeepBasisNet, preset

    torch.manual_seed(0)
    network = DeepBasisNet(preset("tiny", normal_unit_width=4)).eval()
    with torch.no_grad():
        for name, parameter in network.named_parameters():
            if name.endswith(("beta", "gamma")):
                parameter.normal_(0.0, 0.5)
    return network


def assert_the_runs_end_alike(tmp_path) -> None:
    """The runs written to ``tmp_path / "a"`` and ``tmp_path / "b"`` end with the same weights, to the bit."""
    from mideepbasis.model.checkpoint import load_model

    b = load_model(tmp_path / "b" / "run" / "model.safetensors").state_dict()
    for name, value in load_model(tmp_path / "a" / "run" / "model.safetensors").state_dict().items():
        assert torch.equal(value, b[name]), name
