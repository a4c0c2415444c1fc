"""The real-photo protocol (the DeepBasis paper's Table 2): a material captured from one photo of
a calibrated scene must re-render the scene's other photos.

A calibrated scene is a folder of rectified photos of one flat sample taken from several
positions (every pixel a point of the sample square, as if seen from straight above), with the
positions of the camera and the flash for each:

==================  ========================================================================
``NN.png``          the photos, 00, 01, ...: sRGB, square, all the same size
``camera_pos.txt``  one ``x,y,z`` line per photo [cm], in the frame of the sample: the square
                    spans x, y in [-s/2, s/2], +z out of the surface
``light_pos.txt``   the flash, as ``camera_pos.txt`` (beside the lens on a phone)
``image_size.txt``  s, the side of the photographed square [cm]
``parameters.json`` or instead of the three: {"camera_pos": [[x, y, z], ...],
                    "light_pos": [...], "image_size": s}
``truth/``          optional: the sample's true material folder (synthetic scenes)
==================  ========================================================================

The protocol: capture the material from the input photo alone (its field of view and nothing
else known: the flash is searched for), render it at every calibrated position, fit one exposure
scale on the input photo (the one that matches it best in the protocol's measure), and compare the clipped,
sRGB-encoded renders with the other photos at the capture's working resolution: RMSE, FLIP and
SSIM, averaged over the other photos. Naive baselines run beside it: a flat grey material and a
Lambertian one whose albedo is the input photo over the flash's falloff.

Shapes: photos (N, 3, H, W) linear in [0, 1]; positions (N, 3) [patch half-widths].
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from .. import constants
from ..errors import InputError

#: The DeepBasis paper's re-rendering RMSE on its real scenes (Table 2).
PAPER_REAL_RMSE = 0.111

#: Files that make a folder a calibrated scene.
POSITION_FILES = ("camera_pos.txt", "light_pos.txt", "image_size.txt")

#: Farthest a flash may sit from the lens, as a fraction of the camera's height: a phone's flash is
#: beside its lens; a position beyond is a wrong line (another photo's, another frame's).
MAX_FLASH_FROM_LENS = 0.25

#: The flat grey baseline: a flat, rough, grey dielectric.
FLAT_GREY = {"diffuse": 0.5, "roughness": 0.6, "specular": 0.04}


@dataclass(frozen=True)
class CalibratedScene:
    """One calibrated scene (see the module docstring).

    Attributes:
        name: the folder's name.
        photos: the photo files, in order.
        cameras, lights: (N, 3) positions [patch half-widths: the square's half side is 1].
        side_cm: the side of the photographed square [cm].
        truth: the true material folder, or None.
    """

    name: str
    photos: list[Path]
    cameras: torch.Tensor
    lights: torch.Tensor
    side_cm: float
    truth: Path | None = None

    def fov(self, index: int) -> float:
        """The field of view [deg] of photo ``index`` as a capture sees a rectified photo: the
        square framed from the camera's height, 2 atan(1 / z)."""
        return math.degrees(2.0 * math.atan(1.0 / float(self.cameras[index, 2])))


def is_calibrated(data: str | Path) -> bool:
    """Whether ``data`` is a calibrated scene or a folder of them."""
    data = Path(data)
    return _is_scene(data) or (data.is_dir() and any(_is_scene(child) for child in data.iterdir()))


def _is_scene(folder: Path) -> bool:
    return (folder / "parameters.json").is_file() or (folder / POSITION_FILES[0]).is_file()


def scene_folders(data: str | Path) -> list[Path]:
    """The calibrated scenes of ``data``: itself, or its sub-folders that are scenes."""
    data = Path(data)
    if _is_scene(data):
        return [data]
    return sorted(child for child in data.iterdir() if child.is_dir() and _is_scene(child))


def load_scene(folder: str | Path) -> CalibratedScene:
    """Read a calibrated scene; a one-line InputError naming the file and the problem."""
    folder = Path(folder)
    parameters = folder / "parameters.json"
    if parameters.is_file():
        try:
            document = json.loads(parameters.read_text())
            cameras, lights, side = document["camera_pos"], document["light_pos"], document["image_size"]
            cameras, lights = _rows(cameras, parameters), _rows(lights, parameters)
            side = float(side[0] if isinstance(side, list) else side)
        except (ValueError, KeyError, TypeError, IndexError, RecursionError) as error:
            raise InputError(f"{parameters}: not calibrated positions ({type(error).__name__}: {error}); "
                             "expected camera_pos, light_pos (lists of [x, y, z]) and image_size") from None
    else:
        cameras, lights = _read_positions(folder / "camera_pos.txt"), _read_positions(folder / "light_pos.txt")
        side = _read_positions(folder / "image_size.txt", columns=1)[0][0]
    photos = sorted(path for path in folder.iterdir() if path.suffix.lower() == ".png" and path.stem.isdigit())
    if not photos:
        raise InputError(f"{folder}: no photos NN.png")
    numbers = [int(path.stem) for path in photos]
    if numbers != list(range(len(photos))):
        missing = sorted(set(range(max(numbers) + 1)) - set(numbers))
        raise InputError(f"{folder}: photo {missing[0]:02d}.png is missing (the photos are numbered 00, 01, ...)")
    for name, rows in (("camera", cameras), ("light", lights)):
        if len(rows) != len(photos):
            raise InputError(f"{folder}: {len(rows)} {name} positions for {len(photos)} photos")
    if not side > 0:
        raise InputError(f"{folder}: the side of the photographed square must be positive, got {side}")
    half = side / 2.0
    cameras, lights = torch.tensor(cameras) / half, torch.tensor(lights) / half
    for index, (camera, light) in enumerate(zip(cameras, lights)):
        if camera[2] <= 0 or light[2] <= 0:
            raise InputError(f"{folder}: photo {index:02d}: the camera and the flash must be above the sample "
                             f"(z > 0), got z {float(camera[2]) * half:g} and {float(light[2]) * half:g} cm")
        distance = float(torch.linalg.vector_norm(light - camera))
        if distance > MAX_FLASH_FROM_LENS * float(camera[2]):
            raise InputError(f"{folder}: photo {index:02d}: the flash is {distance * half:.2f} cm from the camera, "
                             f"more than {MAX_FLASH_FROM_LENS:g} of its height: a wrong light position "
                             "(a phone's flash sits beside its lens)")
    truth = folder / "truth"
    return CalibratedScene(folder.name, photos, cameras.float(), lights.float(), float(side),
                           truth if truth.is_dir() else None)


def _read_positions(path: Path, columns: int = 3) -> list[list[float]]:
    if not path.is_file():
        raise InputError(f"{path}: missing (a calibrated scene needs {', '.join(POSITION_FILES)} or parameters.json)")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = [float(value) for value in line.replace(",", " ").split()]
        except ValueError:
            values = []
        if len(values) != columns or not all(math.isfinite(v) for v in values):
            raise InputError(f"{path}, line {number}: expected {columns} number(s), got {line.strip()!r}")
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: empty")
    return rows


def _rows(values, source: Path) -> list[list[float]]:
    rows = [[float(value) for value in row] for row in values]
    if any(len(row) != 3 or not all(math.isfinite(v) for v in row) for row in rows):
        raise ValueError("every position must be three finite numbers")
    return rows


# --- rendering the scene's photos -----------------------------------------------------------------


def render_positions(maps: torch.Tensor, scene: CalibratedScene, convention: str) -> torch.Tensor:
    """Linear renders (N, 3, H, W) of maps (10, H, W) at every calibrated position of the scene,
    under one flash intensity (the input photo's exposure fit sets the scale)."""
    from ..render import render_flash

    intensity = math.pi * float(scene.cameras[0, 2]) ** 2  # a white Lambertian below the first camera: about 1
    with torch.no_grad():
        return render_flash(maps[None].float(), scene.lights[None], views=scene.cameras[None], convention=convention,
                            intensity=intensity)[0]


def exposure_scale(render: torch.Tensor, photo: torch.Tensor) -> float:
    """The scale s whose exposed render clip(s render) matches the photo (3, H, W) best in the
    protocol's own measure, the RMSE of clipped sRGB: a search over log s, coarse then fine. (A
    least-squares fit of the linear values is ruled by the few pixels of a sharp highlight, which
    the photo clips and the render does not.)"""
    from ..imageio import linear_to_srgb

    truth = linear_to_srgb(photo.clamp(0.0, 1.0))

    def error(log_scale: float) -> float:
        return float(((linear_to_srgb((render * math.exp(log_scale)).clamp(0.0, 1.0)) - truth) ** 2).mean())

    best, step = 0.0, 1.0
    for _ in range(3):  # steps of e^1, e^0.1, e^0.01 around the best so far
        candidates = [best + step * k for k in range(-10, 11)] if step < 1.0 else [float(k) for k in range(-12, 13)]
        best = min(candidates, key=error)
        step /= 10.0
    return math.exp(best)


def least_squares_scale(render: torch.Tensor, photo: torch.Tensor, clipped: float = 0.98) -> float:
    """The scale s minimising |s render - photo|^2 over the photo's unclipped pixels (3, H, W): the
    plain fit, reported beside (``rmse_least_squares``) because a sharp highlight rules it."""
    keep = (photo < clipped) & (render > 0)
    denominator = float((render[keep] ** 2).sum())
    return float((render[keep] * photo[keep]).sum()) / denominator if denominator > 0 else 1.0


def lambertian_baseline(photo: torch.Tensor, scene: CalibratedScene, index: int, convention: str) -> torch.Tensor:
    """(10, H, W) a flat Lambertian material whose albedo is the photo over the flash's falloff at
    photo ``index``'s position (a white Lambertian rendered there)."""
    height, width = photo.shape[-2:]
    white = constant_material(height, width, diffuse=1.0, roughness=1.0, specular=0.0)
    falloff = render_positions(white, scene, convention)[index]
    material = white.clone()
    material[constants.DIFFUSE] = (photo / falloff.clamp(min=1e-4)).clamp(0.0, 1.0)
    return material


def constant_material(height: int, width: int, diffuse: float, roughness: float, specular: float) -> torch.Tensor:
    """(10, H, W) a flat material of constant maps."""
    maps = torch.empty(constants.BASIS_CHANNELS, height, width)
    maps[constants.NORMAL] = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1)
    maps[constants.DIFFUSE], maps[constants.ROUGHNESS], maps[constants.SPECULAR] = diffuse, roughness, specular
    return maps


@dataclass
class RerenderScores:
    """How a material re-renders a scene's photos other than the input (means over them), and the
    exposure scale fitted on the input."""

    rmse: float
    flip: float
    ssim: float
    exposure: float
    rmse_least_squares: float
    """The RMSE with the exposure fitted by least squares of the linear values instead."""
    renders: torch.Tensor
    """(N, 3, H, W) the exposed, clipped, sRGB-encoded renders at every position."""


def score_rerenders(maps: torch.Tensor, photos: torch.Tensor, scene: CalibratedScene, index: int,
                    convention: str) -> RerenderScores:
    """Score maps (10, H, W) against the scene's linear photos (N, 3, H, W), captured from photo ``index``."""
    from ..imageio import linear_to_srgb
    from .metrics import flip, ssim

    renders = render_positions(maps, scene, convention)
    truth = linear_to_srgb(photos.clamp(0.0, 1.0))
    others = [j for j in range(len(photos)) if j != index]

    def exposed(scale: float) -> tuple[torch.Tensor, float]:  # the renders shown, their mean RMSE
        shown = linear_to_srgb((renders * scale).clamp(0.0, 1.0))
        return shown, float(((shown[others] - truth[others]) ** 2).mean(dim=(1, 2, 3)).sqrt().mean())

    scale = exposure_scale(renders[index], photos[index])
    shown, rmse = exposed(scale)
    _, rmse_least_squares = exposed(least_squares_scale(renders[index], photos[index]))
    return RerenderScores(rmse=rmse, flip=float(flip(truth[others], shown[others]).mean()),
                          ssim=float(ssim(truth[others], shown[others]).mean()), exposure=scale,
                          rmse_least_squares=rmse_least_squares, renders=shown)


# --- the protocol --------------------------------------------------------------------------------

#: The rows of the protocol, in the order of its table.
CAPTURE_ROW, UNREFINED_ROW = "capture (default)", "capture, no refinement"
GREY_ROW, LAMBERTIAN_ROW, TRUTH_ROW = "flat grey", "Lambertian: photo / falloff", "true material"
PAPER_ROW = "the paper's DeepBasis (Table 2)"


def upsampled_row(resolution: int) -> str:
    """The row of a capture at ``resolution`` px whose maps are upsampled to the working resolution."""
    return f"capture at {resolution} px, upsampled"


def materials_of_scene(capturer, scene: CalibratedScene, index: int, photo: torch.Tensor,
                       truth: torch.Tensor | None = None, upsampled_from: int | None = None) -> dict[str, torch.Tensor]:
    """The materials (10, H, W) each row re-renders, captured from photo ``index`` (linear, (3, H,
    W), as capture loads it) of the scene: the capture with and without its refinement (one
    search, one prediction), the baselines, the scene's ``truth`` (``true_maps``) where given, and
    where ``upsampled_from`` is, the whole capture at that working resolution [pixels], its maps
    upsampled to the photo's size."""
    from ..material import Material
    from ..resampling import upsample_maps

    capturer = capturer.with_config(fov=scene.fov(index))
    loaded = capturer.load(scene.photos[index])
    offset = capturer.search(loaded).offset if capturer.config.light is None else capturer.config.light
    prediction = capturer.predict(loaded, offset)
    refined, _ = capturer.refine(prediction, loaded, offset)
    height, width = photo.shape[-2:]

    def as_written(maps: torch.Tensor) -> torch.Tensor:  # repaired as capture writes it
        return Material.from_tensor(maps[0].cpu()).to_tensor()

    materials = {CAPTURE_ROW: as_written(refined.maps), UNREFINED_ROW: as_written(prediction.maps),
                 GREY_ROW: constant_material(height, width, **FLAT_GREY),
                 LAMBERTIAN_ROW: lambertian_baseline(photo, scene, index, capturer.convention)}
    if upsampled_from is not None:
        small = capturer.with_config(resolution=upsampled_from).capture(scene.photos[index]).material.to_tensor()
        materials[upsampled_row(upsampled_from)] = as_written(upsample_maps(small[None], (height, width)))
    if truth is not None:
        materials[TRUTH_ROW] = truth
    return materials


def true_maps(scene: CalibratedScene, size: int) -> torch.Tensor:
    """The scene's true maps (10, size, size), area-averaged to that size (a smaller one)."""
    from ..material import Material
    from ..resampling import downsample_maps

    truth = Material.load(scene.truth).to_tensor()
    if truth.shape[-1] < size:
        raise InputError(f"{scene.truth}: its maps are smaller than the {size} px the photos are compared at "
                         "(evaluate --resolution)")
    return truth if truth.shape[-1] == size else downsample_maps(truth[None], (size, size))[0]


def scene_photos(scene: CalibratedScene, resolution: int | str) -> torch.Tensor:
    """(N, 3, R, R) the scene's photos, linear, as capture loads them (``load_photo``)."""
    from ..capturing.photo import load_photo

    return torch.stack([load_photo(path, fov=scene.fov(0), resolution=resolution)[0] for path in scene.photos])


def evaluate_scene(capturer, scene: CalibratedScene, inputs: list[int], upsampled_from: int | None = None) -> dict:
    """Every row's scores on one scene, averaged over the input photos ``inputs`` (``upsampled_from``:
    ``materials_of_scene``):
    {"rows": {row: {figure: value}}, "per_input": {row: [RMSE of each input, in the order of
    ``inputs``]}, "inputs": inputs, "renders": {row: (N, 3, H, W) sRGB} of the first input,
    "photos": (N, 3, H, W) linear}."""
    from .metrics import map_rmse

    photos = scene_photos(scene, capturer.config.resolution)
    if upsampled_from is not None and upsampled_from >= photos.shape[-1]:
        raise InputError(f"{scene.name}: --upsampled-from {upsampled_from} is not below the working resolution "
                         f"({photos.shape[-1]} px)")
    truth = None if scene.truth is None else true_maps(scene, photos.shape[-1])  # read once
    rows: dict[str, dict[str, list[float]]] = {}
    renders = {}
    for index in inputs:
        if not 0 <= index < len(photos):
            raise InputError(f"{scene.name}: no photo {index:02d} to capture from ({len(photos)} photos)")
        materials = materials_of_scene(capturer, scene, index, photos[index], truth, upsampled_from)
        for row, maps in materials.items():
            scores = score_rerenders(maps, photos, scene, index, capturer.convention)
            figures = {"rmse": scores.rmse, "flip": scores.flip, "ssim": scores.ssim,
                       "rmse_least_squares": scores.rmse_least_squares}
            if truth is not None:
                figures.update({f"{name}_rmse": float(value) for name, value in map_rmse(maps[None], truth[None]).items()})
            for name, value in figures.items():
                rows.setdefault(row, {}).setdefault(name, []).append(value)
            if index == inputs[0]:
                renders[row] = scores.renders
    means = {row: {name: sum(values) / len(values) for name, values in figures.items()} for row, figures in rows.items()}
    per_input = {row: figures["rmse"] for row, figures in rows.items()}
    return {"rows": means, "per_input": per_input, "inputs": list(inputs), "renders": renders, "photos": photos}


def run_real_evaluation(config, out: Path, progress: bool = True) -> dict:
    """The protocol on every calibrated scene of ``config.data`` (an ``EvaluationConfig``): writes
    ``summary.json``, ``table.md`` and ``sheets/<scene>.png`` into ``out``; returns the summary.
    A scene that cannot be read costs its own note; the others run."""
    import time

    from tqdm import tqdm

    from ..capturing import Capturer

    started = time.perf_counter()
    from .run import evaluation_capture_config, shown_refinement

    capture_config = evaluation_capture_config(
        config, network_resolution=config.network_resolution, refine=shown_refinement(config), detail=config.detail,
        **({"resolution": config.resolution} if config.resolution else {}))
    capturer = Capturer(config.model, capture_config)
    folders = scene_folders(config.data)
    if not folders:
        raise InputError(f"{config.data}: no calibrated scenes (folders with {', '.join(POSITION_FILES)})")
    scenes, notes, results = [], [], {}
    for folder in folders:
        try:
            scenes.append(load_scene(folder))
        except InputError as error:
            notes.append(f"skipped: {error}")
    for scene in tqdm(scenes, desc="scenes", unit="scene", disable=not progress):
        inputs = list(range(len(scene.photos))) if config.input_photo == "all" else [int(config.input_photo)]
        try:
            results[scene.name] = evaluate_scene(capturer, scene, inputs, config.upsampled_from)
        except InputError as error:
            notes.append(f"skipped: {error}")
    if not results:
        raise InputError(f"{config.data}: no calibrated scene could be evaluated ({'; '.join(notes)})")
    rows: dict[str, dict[str, float]] = {}
    for result in results.values():
        for row, figures in result["rows"].items():
            for name, value in figures.items():
                rows.setdefault(row, {}).setdefault(name, 0.0)
                rows[row][name] += value / len(results)
    rows[PAPER_ROW] = {"rmse": PAPER_REAL_RMSE}
    summary = {"protocol": "real (calibrated scenes)", "data": str(config.data), "model": config.model or "shipped",
               "input_photo": config.input_photo, "scenes": {name: r["rows"] for name, r in results.items()},
               "per_input": {name: {"inputs": r["inputs"], "rmse": r["per_input"]} for name, r in results.items()},
               "rows": rows, "n_scenes": len(results), "notes": notes,
               "working_resolution": capture_config.resolution,
               "compared_at": {name: int(r["photos"].shape[-1]) for name, r in results.items()},
               "refine": dataclasses.asdict(capture_config.refine),
               "seconds": time.perf_counter() - started}
    write_real_evaluation(out, summary, results)
    return summary


def real_table(summary: dict) -> str:
    """The protocol's table (markdown): the mean over the scenes, then each scene's RMSE."""
    figures = ["rmse", "flip", "ssim", "rmse_least_squares"] + [f"{name}_rmse" for name in constants.MAP_SLICES]
    shown = [name for name in figures if any(name in row for row in summary["rows"].values())]
    lines = [f"Re-rendering the other photos of {summary['n_scenes']} calibrated scene(s), captured from photo "
             f"{summary['input_photo']} (clipped sRGB; exposure fitted on the input for the least RMSE, and by "
             "least squares of the linear values in rmse_least_squares; map RMSE where the truth is known)", "",
             "| row | " + " | ".join(shown) + " |", "|---" * (len(shown) + 1) + "|"]
    for row, values in summary["rows"].items():
        lines.append(f"| {row} | " + " | ".join(f"{values[name]:.4f}" if name in values else "" for name in shown) + " |")
    if summary["n_scenes"] > 1:
        names = list(summary["scenes"])
        lines += ["", "RMSE per scene:", "", "| row | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        for row in next(iter(summary["scenes"].values())):
            lines.append(f"| {row} | " + " | ".join(f"{summary['scenes'][n][row]['rmse']:.4f}" for n in names) + " |")
    for name, per_input in summary.get("per_input", {}).items():
        if len(per_input["inputs"]) < 2:
            continue
        photos = [f"{index:02d}" for index in per_input["inputs"]]
        lines += ["", f"RMSE of {name} per input photo (the material captured from it, the others re-rendered):", "",
                  "| row | " + " | ".join(photos) + " |", "|---" * (len(photos) + 1) + "|"]
        for row, values in per_input["rmse"].items():
            lines.append(f"| {row} | " + " | ".join(f"{value:.5f}" for value in values) + " |")
    return "\n".join(lines) + "\n"


def write_real_evaluation(out: Path, summary: dict, results: dict) -> None:
    """summary.json, table.md and a sheet per scene (the photos, then each capture row's renders)."""
    from ..imageio import linear_to_srgb, write_bytes, write_image

    write_bytes(out / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())
    write_bytes(out / "table.md", real_table(summary).encode())
    for name, result in results.items():
        photos = linear_to_srgb(result["photos"].clamp(0, 1))
        strips = [photos] + [result["renders"][row] for row in (CAPTURE_ROW, UNREFINED_ROW, LAMBERTIAN_ROW)]
        sheet = torch.cat([torch.cat(list(strip), dim=2) for strip in strips], dim=1)
        write_image(out / "sheets" / f"{name}.png", sheet.permute(1, 2, 0).numpy())
