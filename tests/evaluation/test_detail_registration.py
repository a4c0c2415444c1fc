"""``benchmarks/detail.py``'s registration: how a calibrated scene's fine detail lines up across
its photos, on photos that are one texture shifted by known whole pixels."""

import torch

from mideepbasis.imageio import write_image

from ..helpers import benchmark_module
from .test_real import positions_cm


def _write_shifted_scene(folder, shifts, noise):
    """Photos 00 - 08 of one fine texture, photo k rolled by ``shifts[k]`` (dy, dx) [pixels] with
    its own noise of ``noise`` (linear), and the calibrated layout's position files."""
    generator = torch.Generator().manual_seed(3)
    texture = 0.3 + 0.2 * torch.rand(1, 128, 128, generator=generator)
    folder.mkdir(parents=True)
    for index, (dy, dx) in enumerate(shifts):
        photo = torch.roll(texture, shifts=(dy, dx), dims=(1, 2)).expand(3, -1, -1)
        photo = photo + noise * torch.randn(3, 128, 128, generator=generator)
        write_image(folder / f"{index:02d}.png", photo.clamp(0, 1).permute(1, 2, 0).numpy(), encode_srgb=True)
    lines = "".join(",".join(f"{v:.5f}" for v in row.tolist()) + "\n" for row in positions_cm())
    (folder / "camera_pos.txt").write_text(lines)
    (folder / "light_pos.txt").write_text(lines)
    (folder / "image_size.txt").write_text("8.0\n")
    return folder


def test_registration_finds_each_photos_shift_and_how_much_noise_hides(tmp_path):
    detail = benchmark_module("detail")
    shifts = [(0, 0), (0, 0), (1, 0), (0, -2), (3, 1), (0, 0), (-1, -1), (2, 2), (0, 5)]
    clean = detail.registration(_write_shifted_scene(tmp_path / "clean", shifts, 0.0), band=32)
    noisy = detail.registration(_write_shifted_scene(tmp_path / "noisy", shifts, 0.1), band=32)
    assert [tuple(row["shift"]) for row in clean] == shifts[1:]
    assert all(row["peak_correlation"] > 0.98 for row in clean)
    assert clean[0]["correlation"] > 0.99  # photo 01 is photo 00
    assert all(row["correlation"] < 0.3 for row, shift in zip(clean, shifts[1:]) if shift != (0, 0))
    # Noise of the texture's own spread leaves about half the variance to each photo: ~0.5.
    assert all(0.3 < row["peak_correlation"] < 0.7 for row in noisy)
