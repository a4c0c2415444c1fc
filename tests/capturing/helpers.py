"""Shared by the capture tests: an oracle network that predicts the true material, a procedural
material, a photo file."""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from mideepbasis import constants
from mideepbasis.capturing import CaptureConfig, Capturer, Photo, SearchConfig
from mideepbasis.model.network import DeepBasisNet, DeepBasisOutput, NetworkConfig, preset, to_signed


class OracleModel(DeepBasisNet):
    """Predicts the true material whatever it is shown (one basis: global mean plus per-pixel deviations).

    It isolates the lighting search and the refinement from the quality of a trained network.
    """

    def __init__(self, truth: torch.Tensor):
        super().__init__(preset("tiny", num_bases=1, use_local=True))
        self.truth = truth
        self.config = NetworkConfig(encoder_channels=(8,), decoder_channels=(), num_bases=1)

    def forward(self, inputs, lights=None, fov=constants.DEFAULT_FOV_DEG):
        signed = to_signed(self.truth)
        global_bases = signed.mean(dim=(2, 3)).view(1, 1, 10)
        deviations = (signed - global_bases.view(1, 10, 1, 1)).view(1, 1, 10, *signed.shape[-2:])
        weights = torch.ones(1, 1, *signed.shape[-2:])
        return DeepBasisOutput(maps=maps_by_hand(global_bases, deviations), weights=weights, global_bases=global_bases,
                               deviations=deviations)


def maps_by_hand(global_bases: torch.Tensor, deviations: torch.Tensor) -> torch.Tensor:
    """The maps of one basis with weight 1, written out here (not through the package's blend):
    signed basis = global + deviation, its normal part unit length with z >= 0, the other seven
    channels mapped from [-1, 1] to [0, 1]."""
    signed = global_bases.view(1, 10, 1, 1) + deviations[:, 0]
    normal = signed[:, :3] / signed[:, :3].norm(dim=1, keepdim=True)
    normal = torch.cat([normal[:, :2], normal[:, 2:].clamp(min=0.0)], dim=1)
    normal = normal / normal.norm(dim=1, keepdim=True)
    return torch.cat([normal, (signed[:, 3:].clamp(-1.0, 1.0) * 0.5 + 0.5).clamp(0.0, 1.0)], dim=1)


def oracle_search(truth, photo, config: SearchConfig):
    """The lighting search of capture's engine, with the oracle as its network."""
    return Capturer(OracleModel(truth), CaptureConfig(search=config)).search(Photo(photo, 45.0, "argument"))


def material(seed=3, size=64):
    from mideepbasis.data.procedural import GeneratorConfig, generate

    return generate(seed, config=GeneratorConfig(size=size, mix_probability=0.0, weathering=False)).to_tensor()[None]



def photo_file(tmp_path, name="photo.jpg", size=(96, 80), focal=None, value=0.4):
    pixels = (np.random.default_rng(0).uniform(0.2, 0.8, size[::-1] + (3,)) * 255 * value / 0.4).clip(0, 255)
    image = Image.fromarray(pixels.astype(np.uint8))
    exif = Image.Exif()
    if focal:
        exif.get_ifd(0x8769)[0xA405] = focal
    path = tmp_path / name
    image.save(path, exif=exif)
    return path


def encode(photos, lights, model):
    from mideepbasis.model.inputs import encode_inputs

    return encode_inputs(photos, lights, 45.0, model.config.convention, model.config.plane_extent,
                         model.config.extra_inputs)
