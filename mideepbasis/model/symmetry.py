"""The symmetries of the capture: the square sample under a camera and flash above its centre is
unchanged by the eight rotations and mirrorings of the square (the dihedral group D4), so a
network's answer for a photo and for the photo turned or mirrored (with its flash position turned
the same way) should agree once turned back. Averaging the answers over the group (test-time
augmentation) removes the part of a trained network's error that breaks the symmetry.

Coordinates as in ``geometry.pixel_points``: x grows with the column, y with decreasing row. A
symmetry is applied as an optional transpose, then an optional mirror of the columns, then of the
rows. On the plane they are the maps (x, y) -> (-y, -x), x -> -x and y -> -y; every one is its own
inverse, so a symmetry is undone by applying its steps in the reverse order.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from .. import constants
from .inputs import RELIEF_DIRECTION_CHANNEL, decode_photo
from .network import DeepBasisNet, DeepBasisOutput, add_slope, normalize_basis_normals, to_maps


@dataclass(frozen=True)
class Symmetry:
    """One element of D4, as the steps that make it."""

    transpose: bool = False
    """Swap rows and columns first: (x, y) -> (-y, -x) on the plane. Needs a square image."""

    mirror_columns: bool = False
    """Then reverse the columns: x -> -x."""

    mirror_rows: bool = False
    """Then reverse the rows: y -> -y."""

    def steps(self) -> list[str]:
        return [name for name, on in (("transpose", self.transpose), ("columns", self.mirror_columns),
                                      ("rows", self.mirror_rows)) if on]

    def image(self, image: torch.Tensor, inverse: bool = False) -> torch.Tensor:
        """(..., H, W) images moved by the symmetry (or by its inverse)."""
        for step in (reversed(self.steps()) if inverse else self.steps()):
            image = _IMAGE_STEPS[step](image)
        return image

    def vectors(self, vectors: torch.Tensor, dim: int = 1, inverse: bool = False) -> torch.Tensor:
        """Vectors whose first two components along ``dim`` are x and y on the plane (a flash
        position (B, 3), a slope field (B, 2, H, W)), their x and y moved by the symmetry (or by its
        inverse); further components (z) are kept."""
        x, y = vectors.narrow(dim, 0, 1), vectors.narrow(dim, 1, 1)
        for step in (reversed(self.steps()) if inverse else self.steps()):
            x, y = _VECTOR_STEPS[step](x, y)
        return torch.cat([x, y, vectors.narrow(dim, 2, vectors.shape[dim] - 2)], dim=dim)

    def field(self, field: torch.Tensor, inverse: bool = False) -> torch.Tensor:
        """A vector field (B, 2+, H, W) moved as a whole: its pixels and its vectors."""
        return self.vectors(self.image(field, inverse), dim=1, inverse=inverse)

    def image_with_vector(self, image: torch.Tensor, vector_channel: int) -> torch.Tensor:
        """(..., C, H, W) an image moved with the in-plane vector whose x and y are channels
        ``vector_channel`` and ``vector_channel + 1`` (a normal, a flash direction): its pixels,
        and those two channels as vectors; a new tensor."""
        moved = self.image(image)
        before, vector, after = moved.split([vector_channel, 2, moved.shape[-3] - vector_channel - 2], dim=-3)
        return torch.cat([before, self.vectors(vector, dim=-3), after], dim=-3)


_IMAGE_STEPS = {"transpose": lambda image: image.transpose(-1, -2),
                "columns": lambda image: image.flip(-1),
                "rows": lambda image: image.flip(-2)}
_VECTOR_STEPS = {"transpose": lambda x, y: (-y, -x),
                 "columns": lambda x, y: (-x, y),
                 "rows": lambda x, y: (x, -y)}

#: The group by how many of its elements are used: 1 the identity, 2 and a mirror of the columns,
#: 4 the mirrorings (and the half turn), 8 the whole group (needs square images).
SYMMETRY_SETS = {
    1: (Symmetry(),),
    2: (Symmetry(), Symmetry(mirror_columns=True)),
    4: tuple(Symmetry(False, c, r) for c in (False, True) for r in (False, True)),
    8: tuple(Symmetry(t, c, r) for t in (False, True) for c in (False, True) for r in (False, True)),
}


def symmetrised_field(function: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], image: torch.Tensor,
                      lights: torch.Tensor, count: int = 8) -> torch.Tensor:
    """The mean over ``count`` symmetries (``SYMMETRY_SETS``) of ``function(image, lights)``, a
    vector field (B, 2+, H, W) whose first two channels are x and y on the plane, each answer
    computed on the moved image and flash and moved back. All the moved inputs go through
    ``function`` as one batch.

    Args:
        function: (images (B', C, H, W), lights (B', 3)) -> vector field (B', 2+, H, W).
        image: (B, C, H, W) images of the sample (square where ``count`` is 8).
        lights: (B, 3) flash positions [patch half-widths].
    """
    group = symmetry_group(count, *image.shape[-2:])
    if count == 1:
        return function(image, lights)
    moved = function(torch.cat([s.image(image) for s in group]), torch.cat([s.vectors(lights, dim=1) for s in group]))
    return mean_moved_back(group, moved, "field")



def _plane_matrix(symmetry: Symmetry) -> tuple[int, ...]:
    """The symmetry's action on the plane's (x, y), a 2 x 2 integer matrix, row by row."""
    images = symmetry.vectors(torch.eye(2), dim=1).round().int()  # rows: the images of (1, 0) and (0, 1)
    return tuple(images.T.flatten().tolist())


def mirror_and_turns(mirror: bool, turns: int) -> Symmetry:
    """The symmetry that mirrors the sample left-right (x -> -x) when ``mirror``, then turns it by
    ``turns`` quarter turns counter-clockwise ((x, y) -> (-y, x)): how training draws its moves."""
    c, s = ((1, 0), (0, 1), (-1, 0), (0, -1))[turns % 4]  # cos and sin of the turn
    m = -1 if mirror else 1
    target = (c * m, -s, s * m, c)  # turn @ mirror
    return next(symmetry for symmetry in SYMMETRY_SETS[8] if _plane_matrix(symmetry) == target)


def dihedral(image: torch.Tensor, vector_channel: int | None, mirror: bool, turns: int) -> torch.Tensor:
    """An image of the sample plane moved by ``mirror_and_turns(mirror, turns)``, with the in-plane
    vector whose x and y are channels ``vector_channel`` and ``vector_channel + 1`` (None: no
    vector) moved with it (a normal, a direction). A flash photo of the material so moved, under
    the flash so moved, is the photo so moved.

    Args:
        image: (..., C, H, W), square; returned as a new tensor.
    """
    symmetry = mirror_and_turns(mirror, turns)
    if vector_channel is not None:
        return symmetry.image_with_vector(image, vector_channel)
    moved = symmetry.image(image).contiguous()  # a transpose is a view, the identity the image itself: copied
    return moved.clone() if moved.untyped_storage().data_ptr() == image.untyped_storage().data_ptr() else moved


def check_symmetries(count) -> int:
    """``count`` if it is a count of ``SYMMETRY_SETS``, else a one-line ValueError."""
    if count not in SYMMETRY_SETS:
        raise ValueError(f"symmetries must be one of {', '.join(map(str, SYMMETRY_SETS))}, got {count!r}")
    return count


def parse_symmetries(text: str) -> int:
    """A count of symmetries from the command line (``check_symmetries``)."""
    return check_symmetries(int(text))


def symmetry_group(count: int, height: int, width: int) -> tuple[Symmetry, ...]:
    """``SYMMETRY_SETS[count]`` for an image of height x width, checked."""
    check_symmetries(count)
    if count == 8 and height != width:
        raise ValueError(f"symmetries: 8 needs a square image, got {height}x{width}")
    return SYMMETRY_SETS[count]


#: How each kind of tensor moves: ``image`` (..., H, W) pixels alone; ``field`` (B, 2+, H, W) pixels
#: and the x and y of dim 1; ``basis_field`` (B, N, 3+, H, W) pixels and the normal's x and y of
#: dim 2; ``bases`` (B, N, 10) the normal's x and y of dim 2.
_MOVES = {
    "image": lambda s, value: s.image(value, inverse=True),
    "field": lambda s, value: s.field(value, inverse=True),
    "basis_field": lambda s, value: s.vectors(s.image(value, inverse=True), dim=2, inverse=True),
    "bases": lambda s, value: s.vectors(value, dim=2, inverse=True),
}


def sum_moved_back(group: tuple[Symmetry, ...], value: torch.Tensor, kind: str) -> torch.Tensor:
    """The answers for the moved copies of a batch, stacked along dim 0 in the order of ``group``
    (S x B items), each moved back by its symmetry's inverse (as a ``kind`` of ``_MOVES``) and
    summed: (B, ...)."""
    parts = value.chunk(len(group), dim=0)
    total = None
    for symmetry, part in zip(group, parts, strict=True):
        back = _MOVES[kind](symmetry, part)
        total = back if total is None else total + back
    return total


def mean_moved_back(group: tuple[Symmetry, ...], value: torch.Tensor, kind: str) -> torch.Tensor:
    """``sum_moved_back`` divided by the number of symmetries: their mean, (B, ...)."""
    return sum_moved_back(group, value, kind) / len(group)


# --- the symmetrised prediction -------------------------------------------------------------------

#: Moved copies of a photo ``symmetrised_prediction`` runs through the network at a time. A
#: capture's prediction at 128 px on 2 cores (8 symmetries, the shipped model, medians of 7): chunks
#: of 1 / 2 / 4 / 8 took 578 / 412 - 430 / 340 - 383 / 441 - 463 ms (one copy alone: 90 ms).
SYMMETRY_CHUNK = 4


def symmetrised_prediction(network: DeepBasisNet, inputs: torch.Tensor, lights: torch.Tensor | None,
                           fov: float = constants.DEFAULT_FOV_DEG, with_normal_unit: bool = True,
                           symmetries: int = 8) -> DeepBasisOutput:
    """``network``'s answer for ``inputs`` (B, C, H, W) under flashes at ``lights`` (B, 3) averaged
    over ``symmetries`` turns and mirrorings of the square sample (``SYMMETRY_SETS``; 8 needs
    square inputs); ``DeepBasisNet.symmetrised``. The network runs on batches of the moved inputs
    and flashes (``SYMMETRY_CHUNK`` copies at a time); each part of its answer is moved back and
    averaged slot by slot:

    - the weights, and the diffuse, roughness and specular of the global bases and of the
      deviations, as they are;
    - the normals of the bases as vector fields: each basis's whole normal, global plus
      deviation (the sum ``forward`` adds the slope to and then makes unit), is turned back and
      averaged, and kept as a deviation from the global normals of the photo as it is. The
      global unit gives a slot the same normal whichever way the photo is turned (it moves by
      about 0.004 when the photo does; turning it back would move it by 0.2 - 0.6), so its
      normals cannot be averaged apart from the deviations that turn them;
    - the normal unit's slope, shared by the bases, averaged apart and added after
      (``symmetrised_slope``).

    With one symmetry (the identity alone) this is ``forward`` to float rounding.

    Without a local unit the global normals, all there is, are turned back and averaged.

    The result is a basis output like any other (its global bases can be refined), without the
    per-pixel bases, which only training reads: this is for inference. Every input
    channel must move with the photo: the photo, its log, the lighting mark and the
    ``extra_inputs`` do, made pixel by pixel from the photo and the flash."""
    group = symmetry_group(symmetries, *inputs.shape[-2:])
    batch = inputs.shape[0]
    sums, identity_normals = {}, None
    # A few moved copies at a time: at 128 px a batch of 8 runs slower per photo than one of 4
    # (the activations leave the cache), and fewer of them are held at once.
    for start in range(0, len(group), SYMMETRY_CHUNK):
        chunk = group[start:start + SYMMETRY_CHUNK]
        moved_lights = None if lights is None else torch.cat([s.vectors(lights, dim=1) for s in chunk])
        parts = _moved_parts(network, torch.cat([s.image(inputs) for s in chunk]), moved_lights, fov)
        if identity_normals is None and "global_bases" in parts:
            identity_normals = parts["global_bases"][0][:batch, :, constants.NORMAL]
        for name, (value, kind) in parts.items():
            total = sum_moved_back(chunk, value, kind)
            sums[name] = total if name not in sums else sums[name] + total
    mean = {name: total / len(group) for name, total in sums.items()}
    # The normal unit's relief inputs are made from the photo and the flash alone: once for every
    # symmetry, after the chunks.
    if with_normal_unit and hasattr(network, "normal_unit"):
        mean["slope"] = symmetrised_slope(network, inputs, lights, fov, group)
    if "signed" in mean:  # a direct network: its maps
        return DeepBasisOutput(maps=to_maps(mean["signed"]), signed=mean["signed"])
    reflectance = mean["global_bases"][:, :, constants.REFLECTANCE]
    if "basis_normals" not in mean:  # no local unit: the global normals are all there is, turned back
        global_bases = torch.cat([mean["global_bases"][:, :, constants.NORMAL], reflectance], dim=2)
        return DeepBasisOutput.from_bases(mean["weights"], normalize_basis_normals(global_bases, dim=2))
    # The normals of the photo as it is; the bases' whole normals averaged, kept as deviations from them.
    global_bases = torch.cat([identity_normals, reflectance], dim=2)
    deviations = torch.cat([mean["basis_normals"] - identity_normals[..., None, None],
                            mean["reflectance_deviations"]], dim=2)
    if "slope" in mean:
        deviations = add_slope(global_bases, deviations, mean["slope"], network.config.normal_slope_scaled)
    return DeepBasisOutput.from_bases(mean["weights"], global_bases, deviations, keep_bases=False,
                                      error=mean["error"])


def symmetrised_slope(network: DeepBasisNet, inputs: torch.Tensor, lights: torch.Tensor, fov: float,
                      group: tuple[Symmetry, ...]) -> torch.Tensor:
    """``network``'s normal unit's slope (B, 2, H, W) for ``inputs`` (B, C, H, W) averaged over
    the symmetries of ``group``. Its relief inputs are made pixel by pixel from the photo and the
    flash, with a symmetric blur, so the moved photo's are the photo's moved (to float rounding):
    they are made once, of the photo as it is, and moved. All the moved copies then go through the
    unit as one batch, which the unit, unlike the rest of the network, runs quicker per photo than
    two of 4. Per prediction of the shipped model at 128 px on two cores: the relief inputs
    41 - 48 -> 13 - 15 ms, the unit 231 - 258 -> 201 - 224 ms."""
    reliefs = network.relief_inputs(decode_photo(inputs), lights.view(inputs.shape[0], 3), fov)
    moved = [torch.cat([symmetry.image_with_vector(relief, RELIEF_DIRECTION_CHANNEL) for symmetry in group])
             .to(inputs.dtype) for relief in reliefs]
    return sum_moved_back(group, network.octave_slope(moved), "field") / len(group)


def _moved_parts(network: DeepBasisNet, inputs: torch.Tensor, lights: torch.Tensor | None,
                 fov: float) -> dict[str, tuple[torch.Tensor, str]]:
    """What ``symmetrised_prediction`` averages of the network's answer to (moved) inputs, by name,
    each with how it moves (``_MOVES``): the signed maps of a direct network; else the weights and
    the global bases, and with a local unit each basis's normal sum (global plus deviation,
    (B, N, 3, H, W)), its reflectance deviations ((B, N, 7, H, W)) and the error map. (The normal
    unit's slope is averaged apart: ``symmetrised_slope``.)"""
    stage = network.basis_stage(inputs, lights, fov)
    if isinstance(stage, DeepBasisOutput):
        if stage.weights is None:
            return {"signed": (stage.signed_maps, "field")}
        return {"weights": (stage.weights, "image"), "global_bases": (stage.global_bases, "bases")}
    deviations = network.local_deviations(stage.local_inputs, stage.weights, stage.global_bases)
    # Global plus deviation as they are (not made unit): the slope is added to that sum, as in
    # ``forward``. The normals and the reflectance apart: only the normals' x and y turn.
    normals = stage.global_bases[:, :, constants.NORMAL, None, None] + deviations[:, :, constants.NORMAL]
    return {"weights": (stage.weights, "image"), "global_bases": (stage.global_bases, "bases"),
            "basis_normals": (normals, "basis_field"),
            "reflectance_deviations": (deviations[:, :, constants.REFLECTANCE], "image"),
            "error": (stage.error, "image")}
