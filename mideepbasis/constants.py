"""Capture geometry, shading and I/O defaults: every default lives here, once.

Units are given in brackets. Distances are in patch half-widths: the sample is
the square [-1, 1]^2 in the plane z = 0 (docs/ARCHITECTURE.md section 3).
"""

from __future__ import annotations

import math

# --- capture geometry --------------------------------------------------------------------------

#: Default field of view of the capture camera along the image width [deg].
DEFAULT_FOV_DEG = 45.0

#: Largest hand-held offset of the co-located camera and flash from the ideal, centred capture,
#: measured as the angle atan(|t| / H) seen from the sample centre [deg] (DeepBasis: delta).
MAX_OFFSET_DEG = 16.33

#: Training offsets are drawn per axis from N(0, (delta / OFFSET_SIGMA_DIVISOR)^2) and clipped at delta.
OFFSET_SIGMA_DIVISOR = 3.0

#: Relative luminance of linear sRGB / Rec. 709 primaries (weights sum to 1, so a grey of value g
#: has luminance g; this keeps the scalar metallic equations of ``Material.to_pbr`` exact).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)

#: Default working resolution of captures and training crops [pixels].
DEFAULT_RESOLUTION = 256

#: Turns and mirrorings of the photo a capture's prediction is averaged over (1, 2, 4 or 8;
#: ``DeepBasisNet.symmetrised``). 8: re-render RMSE 0.1120 -> 0.1112 on held-out procedural
#: materials, 0.0910 -> 0.0899 on the shared test set (benchmarks/symmetries.py), for eight
#: network passes instead of one.
DEFAULT_SYMMETRIES = 8


def camera_height(fov_deg: float = DEFAULT_FOV_DEG) -> float:
    """Height H of the camera above the sample so that the sample fills the frame.

    Args:
        fov_deg: field of view along the image width [deg].

    Returns:
        H = 1 / tan(fov / 2) [patch half-widths].
    """
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"field of view must lie in (0, 180) degrees, got {fov_deg}")
    return 1.0 / math.tan(math.radians(fov_deg) / 2.0)


# --- shading -------------------------------------------------------------------------------------

#: The shading conventions every renderer, reader and checkpoint names (docs/ARCHITECTURE.md section 4).
CONVENTIONS = ("physical", "deepbasis")

#: The convention used where none is given.
DEFAULT_CONVENTION = "physical"

#: Clamp applied by the `deepbasis` convention to every cosine before use [unitless].
DEEPBASIS_COSINE_EPS = 1e-12

#: Smallest roughness the `deepbasis` convention lets through [unitless].
DEEPBASIS_MIN_ROUGHNESS = 1e-3

#: Radiant intensity of the `deepbasis` lamp [relative]; their networks were trained with 1.
DEEPBASIS_LAMP_INTENSITY = 1.0

#: Lighting-mark reference material: diffuse albedo, specular albedo (F0) and roughness [unitless].
LIGHTING_MARK_DIFFUSE = 0.1
LIGHTING_MARK_SPECULAR = 0.5
LIGHTING_MARK_ROUGHNESS = 0.15

#: Smallest roughness the `physical` convention lets through, so alpha = r^2 stays a normal
#: float32 and the GGX peak stays finite [unitless].
PHYSICAL_MIN_ROUGHNESS = 1e-3

# --- basis model ---------------------------------------------------------------------------------

#: Number of basis materials N.
NUM_BASES = 10

#: Parameters of one basis material: normal 3, diffuse 3, roughness 1, specular 3.
BASIS_CHANNELS = 10

#: The 10-channel layout of maps (B, 10, H, W) and bases (..., 10, ...), written down once:
#: the channels of each map, and the reflectance parameters (everything after the normal).
NORMAL = slice(0, 3)
DIFFUSE = slice(3, 6)
ROUGHNESS = slice(6, 7)
SPECULAR = slice(7, 10)
REFLECTANCE = slice(3, 10)

#: The lowest specular albedo F0 of a capture's maps (``CaptureConfig.specular_floor``) [linear reflectance]:
#: water's (index of refraction 1.33), below every real surface's. The procedural generator's and the
#: shared test set's speculars start above it (0.026, 0.031).
SPECULAR_FLOOR = 0.02

#: The factor of a capture's normal slopes (``CaptureConfig.normal_strength``). On photos as phones take them the
#: network's relief is too strong: 0.75 lowered the held-out phone scenes' normal error (0.0715 -> 0.0705) and
#: their re-rendering error (0.0894 -> 0.0893; 0.5: 0.0897), and kept the shared 84's normal within its bound
#: (0.0657 -> 0.0660; benchmarks/README.md, refinement_real).
NORMAL_STRENGTH = 0.75

#: The specular lobe's channels, roughness and specular (contiguous in the layout).
LOBE = slice(6, 10)

#: The share of the network's per-pixel variation of the specular lobe that a capture keeps
#: (``CaptureConfig.lobe_variation``). One flash photo shows the lobe only near its highlight, and there the
#: local unit's roughness and specular deviations follow the highlight more than the surface. Chosen on the
#: held-out phone scenes' re-rendering error (1: 0.0893, 0.75: 0.0891, 0.5: 0.0890, 0.25: 0.0891, 0: 0.0900;
#: benchmarks/README.md, refinement_real); it lowered the shared 84's specular error too (0.0392 -> 0.0372).
LOBE_VARIATION = 0.5

#: Split sizes of the normal and the reflectance parameters, for ``tensor.split``.
NORMAL_AND_REFLECTANCE = (3, 7)

#: The maps in layout order, by name.
MAP_SLICES = {"normal": NORMAL, "diffuse": DIFFUSE, "roughness": ROUGHNESS, "specular": SPECULAR}

#: Weight of the variation-consistency loss: L = L_sup + VC_LOSS_WEIGHT * L_vc.
VC_LOSS_WEIGHT = 0.05

# --- rendering -----------------------------------------------------------------------------------

#: Objects a material can be previewed on: the sample on a table, a ball, a cloth draped over one.
PREVIEW_SHAPES = ("plane", "sphere", "cloth")

#: Samples per pixel of path-traced previews.
DEFAULT_SPP = 64

#: Elevation of the environment-preview camera above the sample plane [deg].
PREVIEW_ELEVATION_DEG = 50.0

#: Distance of the environment-preview camera from the sample centre [patch half-widths].
PREVIEW_DISTANCE = 3.4

#: Field of view of the environment-preview camera [deg].
PREVIEW_FOV_DEG = 40.0

#: Resolution of the environment preview [pixels].
PREVIEW_RESOLUTION = 256

#: Sampler and samples per pixel of a capture's environment preview (the sample on a table): 25
#: stratified samples are about as noisy as 64 independent ones, in half the time (sRGB RMSE to
#: a 2,048-spp render on three materials 0.0019 / 0.0135 / 0.0119 against 0.0024 / 0.0141 /
#: 0.0116, 349 - 391 ms against 726 - 830 ms: benchmarks/preview_noise.py). 25 is the square of a
#: prime, as the orthogonal sampler needs.
CAPTURE_PREVIEW_SAMPLER = "orthogonal"
CAPTURE_PREVIEW_SPP = 25

#: Sampler and samples per pixel of a capture's sphere and cloth previews (they cost every
#: capture two more path-traced images). 20 correlated multi-jittered samples are less noisy than
#: the 32 independent ones used before on all six previews measured (sRGB RMSE to a 1,024-spp
#: render, sphere / cloth on three materials: 0.0026 / 0.0022, 0.0099 / 0.0155, 0.0085 / 0.0100
#: against 0.0033 / 0.0027, 0.0106 / 0.0157, 0.0098 / 0.0110) in about 70 % of the time (140 - 188
#: against 203 - 259 ms): benchmarks/preview_noise.py --shapes.
SHAPE_PREVIEW_SAMPLER = "multijitter"
SHAPE_PREVIEW_SPP = 20

#: The film filter of the previews (a capture's, and ``render --light env``'s): ``box`` (each
#: sample in its own pixel), then Mitsuba's Gaussian applied to the image (``render.scenes.
#: render_preview``, ``film_gaussian``) instead of splatted sample by sample into 16 pixels. On
#: two AVX2 cores that saved 50 - 160 ms of each 256 px preview (the three of a capture: 0.3 s),
#: at about the same noise: sRGB RMSE to a 1,024-spp Gaussian-filtered
#: render, plane / sphere / cloth, 0.0021 / 0.0025 / 0.0021, 0.0152 / 0.0108 / 0.0175 and 0.0111 /
#: 0.0088 / 0.0108 on three materials against 0.0020 / 0.0026 / 0.0022, 0.0137 / 0.0099 / 0.0155
#: and 0.0121 / 0.0085 / 0.0100 (benchmarks/preview_noise.py --filters). The second material, the
#: finest, is 7 - 13 % noisier so: fewer samples in the Gaussian film's time would cost it about as
#: much (the noise goes as one over the root of the samples).
PREVIEW_FILM_FILTER = "box"

#: Environment variable that, set to ``1``, makes ``mideepbasis.render`` switch Mitsuba's variant
#: without its Python AD integrators (``render.SKIP_PYTHON_INTEGRATORS``); the console command sets it.
SKIP_MITSUBA_PYTHON_INTEGRATORS_ENV = "MIDEEPBASIS_SKIP_MITSUBA_PYTHON_INTEGRATORS"

# --- image I/O -----------------------------------------------------------------------------------

#: Largest image accepted on read, against decompression bombs [pixels].
MAX_IMAGE_PIXELS = 64 * 1024 * 1024

#: Tolerance on |n| - 1 for a normal to count as unit length [unitless].
UNIT_NORMAL_TOLERANCE = 1e-3

#: Tolerance on the [0, 1] range of diffuse, roughness and specular maps [unitless].
RANGE_TOLERANCE = 1e-4

# --- materials -----------------------------------------------------------------------------------

#: Specular albedo F0 of dielectrics in the metallic-roughness model, and the default specular of
#: constant materials [unitless].
DIELECTRIC_F0 = 0.04

#: The specular F0 up to which the exports keep a pixel a dielectric (metallic 0) [reflectance]. Dielectrics
#: reach about 0.08 (index of refraction 1.8), and KHR_materials_specular's colour factor carries any F0
#: exactly; at 0.04 a glossy dielectric slightly above it turned partly metallic, its specular taking the
#: base colour (the Blender check of a capture: 1.2 % off, 0.6 % at 0.08).
EXPORT_METAL_F0 = 0.08

#: Linear values below this are encoded as if they were this by the refinement's sRGB loss
#: (``RefineConfig.encoded_loss``): the sRGB curve's slope, infinite at 0, would make a black
#: pixel's gradient blow up [linear].
REFINE_ENCODING_FLOOR = 1e-4
