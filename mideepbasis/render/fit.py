"""The refinement's loop on the drjit side: a step of Adam on the global bases, recorded once.

``capture.refine.refine_global_bases`` fits the N global bases of a prediction to the photo. Its
torch loop crosses to drjit and back at every step (the bridge), and the tracing of the plugin's
Python code, not the arithmetic, takes most of each step's 4 - 8 ms at 64 x 64 pixels. Here the
whole step (the blend, the plugin's evaluation, the loss, its gradient and the Adam update) is
one ``dr.freeze`` function: traced at its first call, then replayed as a few kernels.

The same arithmetic as the torch loop (``compose_bases``, ``to_maps``, clipping, mean L1, the
prior, ``SmallAdam``), so the same result to float rounding
(``tests/capturing/test_refine.py::test_the_frozen_drjit_refinement_loop_is_the_torch_loop``). Two
choices keep a step to a few kernels:

- the maps change at every step, and a texture update cannot be recorded: the plugin is evaluated
  with the maps given per pixel (``SVBRDF.eval_maps``);
- the gradient of the N x 10 bases is a sum over every pixel. Each basis value enters the blend
  through its own per-pixel copy (``gather`` of the packed (N x 10) x pixels array, whose
  backward writes each entry once), and one ``block_sum`` turns their gradients into the N x 10
  sums; autodiff through a gather of the N x 10 values themselves would scatter every pixel's
  share into the same few addresses.

When the normals stay as predicted (the default), their blend is the same at every step: it is
made once, before the loop, and a step blends, differentiates and renders the seven other channels
alone (the torch loop does the same). The plugin's gradient with respect to the normal, most of a
step's arithmetic, is then not computed only to be masked out.

Data cross from torch here as numpy arrays, at the start and the end of the loop (the bridge is
the crossing for renders inside torch's autograd).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import constants
from ..imageio import linear_to_srgb
from .bridge import flash_renderer

#: Adam's moment decay rates and epsilon, as ``torch.optim.Adam``'s defaults (``SmallAdam``).
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8


@dataclass
class FitInputs:
    """What a refinement holds fixed, as drjit arrays (a PyTree: the frozen step's input).

    Shapes: N bases, P = r * r pixels (row-major), K = N * 10 basis values (basis-major).
    """

    weights: list
    """N arrays of P: the blending weights (sum 1 per pixel)."""

    deviations: mi.Float
    """K * P: the local deviations, value k of pixel p at k * P + p (signed space); where the
    normals stay, those of the seven ``REFLECTANCE_CHANNELS`` of every basis alone (7 N * P)."""

    predicted: mi.Float
    """K: the network's global bases (signed space)."""

    movable: mi.Float
    """K: 1 where a basis value may move, 0 where it stays as predicted (the normals by default)."""

    target: mi.Color3f
    """P: the photo, linear, area-averaged to r x r."""

    light: mi.Point3f
    """1: the flash position [patch half-widths]."""

    intensity: mi.Float
    """1: the flash intensity (``geometry.flash_intensity``)."""

    lr: mi.Float
    """1: Adam's learning rate at the step."""

    bound: mi.Float
    """1: the largest magnitude of a global basis value (``RefineConfig.unclamped_moves``: 2)."""

    prior: mi.Float
    """1: the weight of the mean L1 pull of the bases toward the predicted ones."""

    normal_strength: mi.Float
    """1: the factor of the blended normals' slopes (``geometry.scaled_slopes``)."""

    normal: mi.Vector3f
    """P: the blended unit normal of the predicted bases where the normals stay (``fixed_normal``);
    a single unused zero where they move."""

    pixel_weights: mi.Float
    """P: each pixel's weight in the loss (mean 1; 0 leaves a pixel out)."""

    tied: mi.Float
    """K: 1 where a value is a specular channel of a basis whose three move together (their
    gradients replaced by their mean), else 0."""

    DRJIT_STRUCT = {"weights": list, "deviations": mi.Float, "predicted": mi.Float, "movable": mi.Float,
                    "target": mi.Color3f, "light": mi.Point3f, "intensity": mi.Float, "lr": mi.Float, "bound": mi.Float,
                    "prior": mi.Float, "normal_strength": mi.Float, "normal": mi.Vector3f, "pixel_weights": mi.Float,
                    "tied": mi.Float}


def _specular_slots() -> np.ndarray:
    """(10,) 1 at the specular channels of a basis."""
    slots = np.zeros(constants.BASIS_CHANNELS, dtype=np.float32)
    slots[constants.SPECULAR] = 1.0
    return slots


#: The signed-space channels the refinement blends at every step when the normals stay.
REFLECTANCE_CHANNELS = range(constants.BASIS_CHANNELS)[constants.REFLECTANCE]


def _blended_normal(values: mi.Float, weights: list, bases: int, pixels: int, strength: mi.Float) -> mi.Vector3f:
    """The blended unit normal per pixel (``to_maps`` of ``compose_bases``) of the per-pixel basis
    values ``values`` (K * P, value k of pixel p at k * P + p), its slopes times ``strength``
    (``geometry.scaled_slopes``)."""
    channels = constants.BASIS_CHANNELS
    index = dr.arange(mi.UInt32, pixels)
    blended = [None] * 3
    for basis in range(bases):
        normal = mi.Vector3f(*[dr.gather(mi.Float, values, (basis * channels + c) * pixels + index) for c in range(3)])
        normal = normal / (dr.norm(normal) + 1e-12)  # normalize_basis_normals
        for c in range(3):
            term = weights[basis] * dr.clip(normal[c], -1.0, 1.0)
            blended[c] = term if blended[c] is None else blended[c] + term
    normal = mi.Vector3f(blended[0], blended[1], dr.maximum(blended[2], 0.0))
    normal = normal / dr.sqrt(dr.maximum(dr.squared_norm(normal), 1e-12))
    normal = mi.Vector3f(normal.x * strength, normal.y * strength, normal.z)
    return normal / dr.sqrt(dr.maximum(dr.squared_norm(normal), 1e-12))


def fixed_normal(data: FitInputs, bases: int, pixels: int) -> mi.Vector3f:
    """The blended unit normal of the predicted bases, evaluated: what every step of a refinement
    that keeps the normals renders."""
    channels = constants.BASIS_CHANNELS
    values = dr.gather(mi.Float, data.predicted, dr.arange(mi.UInt32, bases * channels * pixels) // pixels)
    normal = _blended_normal(values + data.deviations, data.weights, bases, pixels, data.normal_strength)
    dr.eval(normal)
    return normal


def _blend(current: mi.Float, data: FitInputs, bases: int, pixels: int, normals_move: bool):
    """The blended maps of global bases ``current`` (K) plus the deviations, as ``to_maps`` of
    ``compose_bases``: (unit normal, diffuse, roughness, specular) per pixel, and the packed
    per-pixel copies of the blended channels of ``current`` whose gradients are the bases'
    (``_step``): all ten channels where ``normals_move``, else the seven of
    ``REFLECTANCE_CHANNELS``, with ``data.normal`` as the normal."""
    channels = constants.BASIS_CHANNELS
    blended_channels = range(channels) if normals_move else REFLECTANCE_CHANNELS
    count = len(blended_channels)
    # Packed value j: channel first + (j // P) % count of basis j // (count P), pixel j % P; with
    # all ten channels, value j // P of ``current`` itself.
    slot = dr.arange(mi.UInt32, bases * count * pixels) // pixels
    source = slot if normals_move else (slot // count) * channels + blended_channels.start + slot % count
    packed = dr.gather(mi.Float, current, source)
    dr.enable_grad(packed)
    values = packed + data.deviations  # the blended channels' deviations, in the same order
    normal = _blended_normal(values, data.weights, bases, pixels, data.normal_strength) if normals_move else data.normal
    index = dr.arange(mi.UInt32, pixels)
    rest = [None] * len(REFLECTANCE_CHANNELS)
    for basis in range(bases):
        weight = data.weights[basis]
        for position, c in enumerate(REFLECTANCE_CHANNELS):
            value = dr.gather(mi.Float, values, (basis * count + c - blended_channels.start) * pixels + index)
            term = weight * dr.clip(value, -1.0, 1.0)
            rest[position] = term if rest[position] is None else rest[position] + term
    rest = [dr.clip(value * 0.5 + 0.5, 0.0, 1.0) for value in rest]
    return (normal, mi.Color3f(rest[0], rest[1], rest[2]), rest[3], mi.Color3f(rest[4], rest[5], rest[6])), packed


def _encoded(linear):
    """sRGB encoding of linear values in [0, 1] inside the recorded step (``imageio.linear_to_srgb``'s
    curve on drjit arrays), floored as ``capturing.refine.encoded``."""
    linear = dr.maximum(linear, constants.REFINE_ENCODING_FLOOR)
    return dr.select(linear <= 0.0031308, 12.92 * linear, 1.055 * dr.power(linear, 1.0 / 2.4) - 0.055)


def _step(free: mi.Float, first_moment: mi.Float, second_moment: mi.Float, step: mi.Float, data: FitInputs,
          bases: int, size: int, convention: str, extent: float, normals_move: bool = True,
          encoded_loss: bool = False):
    """One refinement step: (the bases after it, Adam's moments, the loss before it). Where
    ``normals_move`` is False the step renders ``data.normal`` and differentiates the other seven
    channels alone (the normals' gradient would be masked out)."""
    pixels = size * size
    channels = constants.BASIS_CHANNELS
    count = bases * channels
    current = data.predicted + (free - data.predicted) * data.movable
    maps, packed = _blend(current, data, bases, pixels, normals_move)
    radiance = flash_renderer(convention).render_maps(*maps, data.light, size, size, data.intensity, extent)
    shown = dr.clip(radiance, 0.0, 1.0)
    if encoded_loss:
        shown = _encoded(shown)
    loss = dr.sum(dr.abs((shown - data.target) * data.pixel_weights), axis=None) / (3 * pixels)
    dr.backward(loss)
    difference = current - data.predicted
    # d/d current of prior * mean |current - predicted| (torch's |x| has gradient 0 at 0)
    prior_gradient = data.prior / count * dr.select(difference > 0, 1.0, dr.select(difference < 0, -1.0, 0.0))
    sums = dr.block_sum(dr.grad(packed), pixels)
    if not normals_move:  # the seven channels' sums of each basis, in their places among its ten
        slot = dr.arange(mi.UInt32, count)
        channel = slot % channels
        blended = channel >= REFLECTANCE_CHANNELS.start
        sums = dr.select(blended, dr.gather(mi.Float, sums, (slot // channels) * len(REFLECTANCE_CHANNELS)
                                            + channel - REFLECTANCE_CHANNELS.start, blended), 0.0)
    gradient = (sums + prior_gradient) * data.movable
    # Tied specular channels: each moved by the mean of its basis's three gradients.
    specular_start = (dr.arange(mi.UInt32, count) // channels) * channels + constants.SPECULAR.start
    tied_mean = sum(dr.gather(mi.Float, gradient, specular_start + c) for c in range(3)) / 3.0
    gradient = dr.select(data.tied > 0, tied_mean, gradient)
    prior_term = data.prior * dr.sum(dr.abs(difference)) / count
    beta1, beta2 = ADAM_BETAS
    first_moment = dr.lerp(first_moment, gradient, 1 - beta1)
    second_moment = second_moment * beta2 + (1 - beta2) * gradient * gradient
    bias_correction1 = 1 - dr.power(beta1, step)
    bias_correction2_sqrt = dr.sqrt(1 - dr.power(beta2, step))
    denominator = dr.sqrt(second_moment) / bias_correction2_sqrt + ADAM_EPS
    free = dr.clip(dr.detach(free) - data.lr / bias_correction1 * first_moment / denominator, -data.bound, data.bound)
    return free, first_moment, second_moment, dr.detach(loss) + prior_term


#: Steps between two waits for the queued steps where a progress bar is shown: the kernels run
#: asynchronously, and the loop, which only queues them, would otherwise finish the bar at once
#: (125 steps in 30 ms) and the work after it. A wait at every step cost 10 - 15 ms of 125 steps'
#: 260 ms on two AVX2 cores.
PROGRESS_SYNC_STEPS = 10

#: The step, recorded at its first call with each (bases, size, convention, extent) and replayed after.
_frozen_step = dr.freeze(_step)


def _aligned(array) -> np.ndarray:
    """A float32 copy of ``array``, flat, its data on a 64-byte boundary. drjit records the frozen
    step again for each new pattern of aligned and unaligned inputs: numpy's own arrays, aligned by
    chance, make a refinement record it anew now and then (9 recordings over 15 refinements, and
    drjit's warning after 10), where aligned ones give the same two recordings to every refinement."""
    array = np.asarray(array, dtype=np.float32).reshape(-1)
    buffer = np.empty(array.size + 16, dtype=np.float32)
    start = (-buffer.ctypes.data % 64) // 4
    result = buffer[start:start + array.size]
    result[:] = array
    return result


def fit_global_bases(weights: np.ndarray, deviations: np.ndarray, predicted: np.ndarray, movable: np.ndarray,
                     target: np.ndarray, light: np.ndarray, intensity: float, convention: str, extent: float,
                     rates: Sequence[float], prior: float, progress=None,
                     every_channel: bool = False, pixel_weights: np.ndarray | None = None,
                     tied: np.ndarray | None = None, encoded_loss: bool = False,
                     bound: float = 1.0, normal_strength: float = 1.0) -> tuple[np.ndarray, list[float]]:
    """Adam on the global bases so the plugin's render of the blend matches the photo.

    Args:
        weights: (N, r, r); deviations: (N, 10, r, r) signed space; predicted: (N, 10) the
            network's global bases; movable: (10,) 1 where a channel may move; target: (3, r, r)
            linear; light: (3,) [patch half-widths]; intensity: the flash's; convention, extent:
            the shading convention and the sample's half-width [patch half-widths]; rates: Adam's
            learning rate at each step, one per step (``refine.step_rates``); prior: as
            ``RefineConfig``; progress: wraps the range of steps (e.g. ``tqdm``), which
            then advances as the steps are computed (``PROGRESS_SYNC_STEPS``);
            every_channel: blend and differentiate all ten channels at every step even where the
            normals stay (the quicker path's reference in the tests); pixel_weights: (r, r) each
            pixel's weight in the loss, mean 1 (None: all 1); tied: (N,) whether each basis's three
            specular channels move together (None: none); encoded_loss: compare sRGB-encoded
            values (the target given linear); bound: the largest magnitude of a basis value;
            normal_strength: the factor of the blended normals' slopes the renders use.

    Returns:
        ((N, 10) the refined bases, the loss at every step).
    """
    bases, size = weights.shape[0], weights.shape[-1]
    count = bases * constants.BASIS_CHANNELS
    as_float = lambda array: mi.Float(_aligned(array))  # noqa: E731
    target = np.asarray(target, dtype=np.float32).reshape(3, -1)
    if encoded_loss:
        target = linear_to_srgb(np.maximum(target, np.float32(constants.REFINE_ENCODING_FLOOR)))
    data = FitInputs(weights=[as_float(w) for w in weights], deviations=as_float(deviations),
                     predicted=as_float(predicted), movable=as_float(np.tile(movable, bases)),
                     target=mi.Color3f(*[as_float(channel) for channel in target]),
                     light=mi.Point3f(*[float(x) for x in np.asarray(light).reshape(3)]),
                     intensity=mi.Float(float(intensity)), lr=mi.Float(float(rates[0]) if len(rates) else 0.0),
                     bound=mi.Float(float(bound)),
                     prior=mi.Float(float(prior)), normal_strength=mi.Float(float(normal_strength)),
                     normal=dr.zeros(mi.Vector3f, 1),
                     pixel_weights=as_float(np.ones((size, size)) if pixel_weights is None else pixel_weights),
                     tied=as_float(np.zeros((bases, constants.BASIS_CHANNELS)) if tied is None else
                                   np.asarray(tied, dtype=np.float32)[:, None] * _specular_slots()))
    normals_move = every_channel or bool(np.any(np.asarray(movable)[constants.NORMAL] != 0))
    if not normals_move:
        data.normal = fixed_normal(data, bases, size * size)
        data.deviations = as_float(np.asarray(deviations)[:, REFLECTANCE_CHANNELS.start:])
    # Arrays of their own: an input that is another input's variable (a copy of the predicted bases,
    # two zero literals merged into one) would record the first step anew at every refinement.
    free = as_float(predicted)
    first_moment, second_moment = as_float(np.zeros(count)), as_float(np.zeros(count))
    # Evaluated inputs (not literals): every call then matches the same recordings.
    dr.make_opaque(free, first_moment, second_moment, data.light, data.intensity, data.lr, data.bound, data.prior,
                   data.normal_strength)
    # The plugin is made outside the recording: made inside, its arrays would be neither inputs nor
    # the step's own, and the first refinement in a process would fail to record.
    flash_renderer(convention)
    losses = []
    for step in (progress or (lambda steps: steps))(range(1, len(rates) + 1)):
        if step > 1 and rates[step - 1] != rates[step - 2]:
            data.lr = mi.Float(float(rates[step - 1]))
            dr.make_opaque(data.lr)  # an input of the recording, not a literal: no new recording
        free, first_moment, second_moment, loss = _frozen_step(free, first_moment, second_moment, mi.Float(step),
                                                                data, bases, size, convention, float(extent),
                                                                normals_move, encoded_loss)
        losses.append(loss)
        if progress and step % PROGRESS_SYNC_STEPS == 0:
            dr.sync_thread()  # the steps run behind the loop: a bar would end before them
    refined = np.array(data.predicted + (free - data.predicted) * data.movable, dtype=np.float32).reshape(bases, constants.BASIS_CHANNELS)
    return refined, [float(loss[0]) for loss in losses]
