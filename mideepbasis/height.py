"""A height map from a normal map: the surface whose slopes the normals are (Frankot and Chellappa
1988, the least-squares integration in the Fourier domain).

Units and axes as the rest of the package (docs/ARCHITECTURE.md section 3): the sample spans
[-1, 1]^2 [patch half-widths], rows run towards -y, heights are in patch half-widths along +z. A
normal n gives the slopes dh/dx = -n_x / n_z and dh/dy = -n_y / n_z. A tileable map is integrated
as periodic; any other as the periodic map of twice its size that mirrors it (the slopes reflected
with their signs), so its edges do not wrap into each other. That mirrored field's spectrum is the
map's cosine and sine transforms, so it is solved at the map's own size (``cosine_transform``).

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


def _makhoul_order(size: int) -> torch.Tensor:
    """The samples' order the cosine transform's FFT takes them in: the even ones, then the odd
    ones reversed."""
    return torch.cat([torch.arange(0, size, 2), torch.arange(1, size, 2).flip(0)])


def _half_pixel_phase(size: int, sign: float, dims: int, dim: int, dtype: torch.dtype) -> torch.Tensor:
    """``exp(sign i pi k / (2 size))``, k = 0 .. size - 1, shaped to broadcast along ``dim`` of
    ``dims`` dimensions."""
    shape = [1] * dims
    shape[dim] = size
    angle = sign * math.pi * torch.arange(size, dtype=dtype) / (2 * size)
    return torch.polar(torch.ones_like(angle), angle).view(shape)


def _from_the_far_end(values: torch.Tensor, dim: int) -> torch.Tensor:
    """``values`` along ``dim`` read as x_(N-k), k = 0 .. N - 1, with x_N = 0: a 0, then the rest
    reversed."""
    rest = values.narrow(dim, 1, values.shape[dim] - 1)
    return torch.cat([torch.zeros_like(values.narrow(dim, 0, 1)), rest.flip(dim)], dim)


def cosine_transform(values: torch.Tensor, dim: int) -> torch.Tensor:
    """The unnormalised DCT-II of ``values`` along ``dim``: ``sum_n x_n cos(pi k (n + 1/2) / N)``,
    k = 0 .. N - 1, by one complex FFT of the same length (Makhoul 1980: the even samples, then the
    odd ones reversed)."""
    size = values.shape[dim]
    spectrum = torch.fft.fft(values.index_select(dim, _makhoul_order(size)), dim=dim)
    return spectrum.mul_(_half_pixel_phase(size, -1.0, values.dim(), dim, values.dtype)).real.contiguous()


def inverse_cosine_transform(coefficients: torch.Tensor, dim: int) -> torch.Tensor:
    """The inverse of ``cosine_transform`` along ``dim``: ``(C_0 + 2 sum_k C_k cos(pi k (n + 1/2)
    / N)) / N``, by one complex inverse FFT."""
    size = coefficients.shape[dim]
    # C_k - i C_(N-k), C_N being 0, turned back by the phase cosine_transform gave it.
    spectrum = torch.complex(coefficients, -_from_the_far_end(coefficients, dim))
    spectrum.mul_(_half_pixel_phase(size, 1.0, coefficients.dim(), dim, coefficients.dtype))
    samples = torch.fft.ifft(spectrum, dim=dim).real
    del spectrum
    return torch.empty_like(samples).index_copy_(dim, _makhoul_order(size), samples)


def sine_transform(values: torch.Tensor, dim: int) -> torch.Tensor:
    """The unnormalised DST-II of ``values`` along ``dim`` on the cosine transform's frequencies:
    ``sum_n x_n sin(pi k (n + 1/2) / N)``, k = 0 .. N - 1 (0 at k = 0). Since sin(pi k (n + 1/2) /
    N) = (-1)^n cos(pi (N - k) (n + 1/2) / N), it is the cosine transform of the alternated values,
    read backwards."""
    size = values.shape[dim]
    shape = [1] * values.dim()
    shape[dim] = size
    signs = 1.0 - 2.0 * (torch.arange(size) % 2).to(values.dtype).view(shape)
    return _from_the_far_end(cosine_transform(values * signs, dim), dim)


def height_from_normals(normal: torch.Tensor, tileable: bool = False) -> torch.Tensor:
    """The height field (1, H, W) [patch half-widths] whose central-difference slopes fit the
    normals (3, H, W) best in the least-squares sense, with zero mean: the inverse of
    ``data.procedural.core.height_to_normal`` (edges repeated, or wrapped where ``tileable``).

    Float32 FFTs. A tileable map is solved on its periodic spectrum; any other on the spectrum of
    its mirrored field, which is its cosine transform (the height and each slope across its own
    axis, even) and sine transform (each slope along its axis, odd): at the map's size, a 4096 px
    map in about 0.3 GB where the mirrored field took 0.9 GB."""
    along_columns, along_rows = (s.float() for s in slopes(normal))
    height, width = along_columns.shape
    if tileable:
        # The central difference's own spectrum, i sin(w): the integrated field's central
        # differences then match the slopes exactly wherever the slopes are consistent.
        u = torch.sin(2.0 * math.pi * torch.fft.rfftfreq(width))[None, :]
        v = torch.sin(2.0 * math.pi * torch.fft.fftfreq(height))[:, None]
        spectrum = torch.fft.rfft2(along_columns).mul_(-1j * u)
        del along_columns
        spectrum.add_(torch.fft.rfft2(along_rows).mul_(-1j * v))
        del along_rows
        denominator = u * u + v * v
        spectrum.div_(denominator.clamp(min=1e-12)).masked_fill_(denominator <= 1e-12, 0)
        field = torch.fft.irfft2(spectrum, s=(height, width))
        return (field - field.mean())[None]
    # The mirrored field (twice the size, period 2N) has frequencies pi k / N; its spectrum there is
    # the cosine transform times 4 and a half-pixel phase for the height, and the sine transform
    # along the slope's axis times -4i and the same phase for a slope. The central difference's
    # i sin(pi k / N) then gives the height's cosine transform as -(u S_x + v S_y) / (u^2 + v^2).
    u = torch.sin(math.pi * torch.arange(width) / width)[None, :]
    v = torch.sin(math.pi * torch.arange(height) / height)[:, None]
    coefficients = cosine_transform(sine_transform(along_columns, 1), 0).mul_(u)
    del along_columns
    coefficients.add_(sine_transform(cosine_transform(along_rows, 1), 0).mul_(v))
    del along_rows
    denominator = u * u + v * v
    coefficients.div_(denominator.clamp(min=1e-12).neg_()).masked_fill_(denominator <= 1e-12, 0)
    field = inverse_cosine_transform(inverse_cosine_transform(coefficients, 0), 1)
    return (field - field.mean())[None]
