"""A height map from a normal map: the surface whose slopes the normals are (Frankot and Chellappa
1988, the least-squares integration in the Fourier domain).

Units and axes as the rest of the package (docs/ARCHITECTURE.md section 3): the sample spans
[-1, 1]^2 [patch half-widths], rows run towards -y, heights are in patch half-widths along +z. A
normal n gives the slopes dh/dx = -n_x / n_z and dh/dy = -n_y / n_z. A tileable map is integrated
as periodic; any other is first mirrored into a periodic one (the slopes reflected with their
signs), so its edges do not wrap into each other.

Shapes: normals (3, H, W) unit vectors; heights (1, H, W).
"""

from __future__ import annotations

import math

import torch

#: The smallest n_z the slopes are taken from: grazing normals would give unbounded slopes.
MIN_NORMAL_Z = 0.05


def slopes(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(dh/dcolumn, dh/drow) per pixel [patch half-widths per pixel] of unit normals (3, H, W)."""
    _, height, width = normal.shape
    nz = normal[2].clamp(min=MIN_NORMAL_Z)
    # x runs with the columns (2 / W per pixel), y against the rows (2 / H per pixel).
    return -normal[0] / nz * (2.0 / width), normal[1] / nz * (2.0 / height)


def height_from_normals(normal: torch.Tensor, tileable: bool = False) -> torch.Tensor:
    """The height field (1, H, W) [patch half-widths] whose central-difference slopes fit the
    normals (3, H, W) best in the least-squares sense, with zero mean: the inverse of
    ``data.procedural.core.height_to_normal`` (edges repeated, or wrapped where ``tileable``).

    Real FFTs in float32, each spectrum worked in place: a 2048 px map (mirrored to 4096 px)
    takes about 0.4 GB."""
    along_columns, along_rows = (s.float() for s in slopes(normal))
    height, width = along_columns.shape
    if not tileable:  # mirror into a periodic field twice the size: h even, its slopes odd
        along_columns = torch.cat([torch.cat([along_columns, -along_columns.flip(1)], 1),
                                   torch.cat([along_columns.flip(0), -along_columns.flip(0).flip(1)], 1)], 0)
        along_rows = torch.cat([torch.cat([along_rows, along_rows.flip(1)], 1),
                                torch.cat([-along_rows.flip(0), -along_rows.flip(0).flip(1)], 1)], 0)
    rows, columns = along_columns.shape
    # The central difference's own spectrum, i sin(w): the integrated field's central differences
    # then match the slopes exactly wherever the slopes are consistent.
    u = torch.sin(2.0 * math.pi * torch.fft.rfftfreq(columns))[None, :]
    v = torch.sin(2.0 * math.pi * torch.fft.fftfreq(rows))[:, None]
    spectrum = torch.fft.rfft2(along_columns).mul_(-1j * u)
    del along_columns
    spectrum.add_(torch.fft.rfft2(along_rows).mul_(-1j * v))
    del along_rows
    denominator = u * u + v * v
    spectrum.div_(denominator.clamp(min=1e-12)).masked_fill_(denominator <= 1e-12, 0)
    field = torch.fft.irfft2(spectrum, s=(rows, columns))[:height, :width]
    return (field - field.mean())[None]
