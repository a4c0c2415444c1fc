"""What happens to surfaces after they are made: scratches, dirt, wear, stains, fingerprints,
and masks for mixing two materials. Each layer takes and returns a ``Surface``."""

from __future__ import annotations

import math

import numpy as np

from .core import MILLIMETRE, Canvas, Surface, hsv_color, normalized, smoothstep


def _is_metal(surface: Surface) -> np.ndarray:
    """(H, W) in [0, 1]: how metallic each pixel looks (F0 well above any dielectric's)."""
    return smoothstep(0.15, 0.35, surface.specular.mean(axis=-1))


def scratches(canvas: Canvas, surface: Surface) -> Surface:
    """Thin straight or gently curved grooves, mostly along one direction (wiping, handling)."""
    count = int(canvas.loguniform(5, 120))
    direction = canvas.uniform(0, math.pi)
    spread = canvas.uniform(0.05, 1.5)
    angles = direction + spread * (canvas.rng.random(count) - 0.5)
    lengths = canvas.rng.uniform(0.03, 0.5, count)
    starts = canvas.rng.random((count, 2))
    ends = starts + lengths[:, None] * np.stack([np.cos(angles), np.sin(angles)], -1)
    mask = np.zeros((canvas.size, canvas.size), np.float32)
    canvas.draw_lines(mask, starts, ends, canvas.rng.uniform(0.3, 1.0, count), canvas.uniform(0.6, 2.0) / canvas.size)
    depth = canvas.uniform(0.01, 0.08) * MILLIMETRE
    metal = _is_metal(surface)
    # On metal a scratch is a bright rough groove; on a coated dielectric it is a pale rough line.
    roughness = surface.roughness + mask * (canvas.uniform(0.1, 0.4)) * (1 - surface.roughness)
    diffuse = surface.diffuse + mask[..., None] * (1 - metal[..., None]) * 0.15 * (1 - surface.diffuse)
    return Surface(surface.height - depth * mask, diffuse, roughness, surface.specular, surface.variant)


def dirt(canvas: Canvas, surface: Surface) -> Surface:
    """Grime that collects in low places and in patches: darker, browner, rougher, less specular."""
    blur = canvas.blur(surface.height, 1 / 64)
    cavity = normalized(np.maximum(blur - surface.height, 0))
    patches = canvas.blobs(canvas.uniform(2, 8), sharpness=2.0)
    amount = np.clip(canvas.uniform(0.3, 1.0) * cavity + canvas.uniform(0, 0.6) * (patches - 0.4), 0, 1)
    amount = amount * canvas.uniform(0.3, 0.9)
    grime = hsv_color(canvas.uniform(0.05, 0.12), canvas.uniform(0.3, 0.6), canvas.uniform(0.1, 0.35))
    diffuse = surface.diffuse * (1 - amount[..., None]) + grime * amount[..., None]
    roughness = surface.roughness + amount * (0.9 - surface.roughness)
    specular = surface.specular * (1 - amount[..., None]) + 0.03 * amount[..., None]
    return Surface(surface.height, diffuse, roughness, specular, surface.variant)


def wear(canvas: Canvas, surface: Surface) -> Surface:
    """Rubbing on the high points: polished (smoother), paler, slightly flattened."""
    blur = canvas.blur(surface.height, 1 / 48)
    exposed = normalized(np.maximum(surface.height - blur, 0))
    amount = np.clip(exposed * canvas.uniform(0.5, 1.5) * canvas.blobs(canvas.uniform(1, 4)) * 1.5, 0, 1)
    roughness = surface.roughness * (1 - 0.6 * amount)
    diffuse = surface.diffuse + amount[..., None] * 0.25 * (1 - surface.diffuse) * (1 - _is_metal(surface)[..., None])
    height = surface.height - amount * (surface.height - blur) * 0.5
    return Surface(height, diffuse, roughness, surface.specular, surface.variant)


def stains(canvas: Canvas, surface: Surface) -> Surface:
    """A few dried-liquid stains with darker rims (coffee rings) that change colour and gloss."""
    amount = np.zeros((canvas.size, canvas.size), np.float32)
    for _ in range(int(canvas.uniform(1, 4))):
        centre = canvas.rng.random(2)
        radius = canvas.uniform(0.05, 0.25)
        du = (canvas.u - centre[0] + 0.5) % 1.0 - 0.5 if canvas.tileable else canvas.u - centre[0]
        dv = (canvas.v - centre[1] + 0.5) % 1.0 - 0.5 if canvas.tileable else canvas.v - centre[1]
        distance = np.sqrt(du * du + dv * dv) / radius
        distance = distance + 0.25 * canvas.noise(beta=2.0, low=3, high=30) * 0.3
        body = 1.0 - smoothstep(0.85, 1.0, distance)
        rim = np.exp(-((distance - 0.95) / 0.04) ** 2)
        amount = np.maximum(amount, 0.35 * body + 0.65 * rim)
    amount *= canvas.uniform(0.2, 0.7)
    tint = hsv_color(canvas.uniform(0.02, 0.14), canvas.uniform(0.3, 0.8), canvas.uniform(0.15, 0.5))
    diffuse = surface.diffuse * (1 - amount[..., None]) + surface.diffuse * tint * 1.5 * amount[..., None]
    roughness = surface.roughness + amount * canvas.uniform(-0.3, 0.3)
    return Surface(surface.height, diffuse, roughness, surface.specular, surface.variant)


def fingerprints(canvas: Canvas, surface: Surface) -> Surface:
    """Greasy prints: elliptical patches of ridge loops that raise the roughness of glossy areas."""
    amount = np.zeros((canvas.size, canvas.size), np.float32)
    for _ in range(int(canvas.uniform(1, 5))):
        centre = canvas.rng.random(2)
        angle = canvas.uniform(0, math.pi)
        scale = canvas.uniform(0.03, 0.07)
        du, dv = canvas.u - centre[0], canvas.v - centre[1]
        if canvas.tileable:
            du, dv = (du + 0.5) % 1.0 - 0.5, (dv + 0.5) % 1.0 - 0.5
        a = (du * math.cos(angle) + dv * math.sin(angle)) / scale
        b = (-du * math.sin(angle) + dv * math.cos(angle)) / (scale * 1.4)
        radius = np.sqrt(a * a + b * b)
        ridges = 0.5 + 0.5 * np.sin(2 * math.pi * radius * canvas.uniform(7, 11) + 2.0 * a)
        amount = np.maximum(amount, ridges * (1 - smoothstep(0.7, 1.0, radius)))
    amount *= canvas.uniform(0.3, 0.8)
    roughness = surface.roughness + amount * (0.45 - surface.roughness).clip(0, None)
    return Surface(surface.height, surface.diffuse, roughness, surface.specular, surface.variant)


def unevenness(canvas: Canvas, surface: Surface) -> Surface:
    """A gentle fade of colour and gloss across the sample, as real samples have (batch, wear, sun).

    It also keeps the opposite edges of a plain (non-tileable) material from matching, as they
    do not in a photograph: noise and cells wrap by construction. None on a tileable canvas.
    """
    ramp = canvas.ramp()
    if canvas.tileable:
        return surface
    diffuse = surface.diffuse * (1.0 + canvas.uniform(0.03, 0.1) * canvas.choice([-1.0, 1.0]) * ramp[..., None])
    roughness = surface.roughness + canvas.uniform(0.01, 0.05) * canvas.choice([-1.0, 1.0]) * ramp
    return Surface(surface.height, diffuse, roughness, surface.specular, surface.variant)


#: The weathering layers and the chance that each is applied to a material.
WEATHERING = {"scratches": (scratches, 0.25), "dirt": (dirt, 0.25), "wear": (wear, 0.2),
              "stains": (stains, 0.1), "fingerprints": (fingerprints, 0.1)}


def weather(canvas: Canvas, surface: Surface) -> tuple[Surface, list[str]]:
    """Apply each weathering layer with its chance; returns the surface and the layers applied."""
    applied = []
    for name, (layer, probability) in WEATHERING.items():
        if canvas.chance(probability):
            surface = layer(canvas, surface)
            applied.append(name)
    return surface, applied


def mixing_mask(canvas: Canvas) -> tuple[np.ndarray, str]:
    """(H, W) mask in [0, 1] for mixing two materials, and its kind: patches, a noisy split,
    stripes or spots."""
    kind = canvas.choice(["patches", "split", "stripes", "spots"])
    softness = canvas.loguniform(0.02, 0.3)
    if kind == "patches":
        field = canvas.noise(beta=2.5, low=1, high=24)
        threshold = canvas.uniform(-0.8, 0.8)
    elif kind == "split":
        angle = canvas.uniform(0, 2 * math.pi)
        ramp = np.cos(angle) * (canvas.u - 0.5) + np.sin(angle) * (canvas.v - 0.5)
        if canvas.tileable:
            ramp = np.sin(2 * math.pi * ((canvas.u if abs(math.cos(angle)) > 0.7 else canvas.v)))
        field = ramp / max(float(ramp.std()), 1e-6) + 0.4 * canvas.noise(beta=2.0, low=2, high=40)
        threshold = canvas.uniform(-0.5, 0.5)
    elif kind == "stripes":
        cycles = canvas.frequency(canvas.uniform(2, 12))
        axis = canvas.u if canvas.chance(0.5) else canvas.v
        field = np.sin(2 * math.pi * cycles * axis) + 0.2 * canvas.noise(beta=2.0, low=2, high=32)
        threshold = canvas.uniform(-0.5, 0.5)
    else:
        field = canvas.noise(beta=0.0, low=canvas.uniform(6, 20), high=canvas.uniform(24, 40))
        threshold = canvas.uniform(1.0, 2.0)
    return smoothstep(threshold - softness, threshold + softness, field).astype(np.float32), kind
