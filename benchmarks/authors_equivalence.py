"""Our `paper` network with imported weights against the DeepBasis authors' own network code.

    .venv/bin/python benchmarks/authors_equivalence.py --authors-repo PATH [-o benchmarks/results/authors_equivalence.json]

PATH is a checkout of the authors' repository (github.com/CGLiWang/DeepBasis_SVBRDF), which is not
part of this project and is only imported from where it lies. The script builds their GlobalNet and
LocalNet with seeded random weights, saves them as their ``net_g``/``net_l`` state dicts, imports
them with ``mideepbasis import-weights``' code, runs both networks on the same input (the input
construction and the centred-flash geometry of their test code, their renderer for their side) and
reports the largest differences of the lighting mark, weights, global bases, error map, local
deviations and blended maps.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import types
from pathlib import Path

import mideepbasis  # noqa: F401
import torch
from common import RESULTS, write_report

from mideepbasis import constants

CAMERA_HEIGHT = 2.414  # their fovZ for a 45 degree field of view


def authors_modules(repo: Path):
    """Import their network and renderer from their checkout (stubbing imports their renderer does not use)."""
    sys.modules.setdefault("regex", types.SimpleNamespace(D=None))
    sys.modules.setdefault("utils", types.SimpleNamespace(img2tensor=None))
    sys.path.insert(0, str(repo))
    sys.path.insert(0, str(repo / "utils"))
    from network.deepbasis_net import GlobalNet, LocalNet  # noqa: E402
    from render_util import svBRDF  # noqa: E402

    return GlobalNet, LocalNet, svBRDF


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--authors-repo", type=Path, required=True)
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "authors_equivalence.json")
    args = parser.parse_args()
    GlobalNet, LocalNet, svBRDF = authors_modules(args.authors_repo)

    torch.manual_seed(0)
    global_net, local_net = GlobalNet().eval(), LocalNet().eval()
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():  # their initialisation is nearly zero in places: add seeded noise everywhere
        for network in (global_net, local_net):
            for parameter in network.parameters():
                parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator))

    renderer = svBRDF({"nbRendering": 1, "size": 256, "split_num": 5, "split_axis": 1, "concat": True,
                       "svbrdf_norm": True, "permute_channel": True, "order": "pndrs", "lampIntensity": 1})
    camera = torch.tensor([[0.0, 0.0, CAMERA_HEIGHT]])
    light_dir, view_dir, _, _ = renderer.torch_generate(camera, camera, pos=renderer.surface(384, 1.5))
    window = (slice(None), slice(None), slice(64, 320), slice(64, 320))  # the centred 256-pixel crop
    light_dir, view_dir = light_dir[window], view_dir[window]
    distance = torch.ones_like(view_dir[:, 2:3])  # unused by their renderer (no falloff)

    photo = torch.nn.functional.interpolate(torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(2)),
                                            size=256, mode="bilinear", align_corners=False)
    eps = 1e-2
    log_photo = (torch.log(photo + eps) - math.log(eps)) / (math.log(1 + eps) - math.log(eps))
    reference = torch.cat([torch.tensor([0.0, 0.0, 1.0]), torch.full((3,), 0.2 - 1), torch.tensor([0.3 - 1]),
                           torch.full((3,), 0.0)]).view(10, 1, 1).expand(10, 256, 256)
    mark = renderer._render(reference, light_dir, view_dir, distance).squeeze(1).clamp(0, 1)
    inputs = torch.cat([photo, log_photo, mark], 1) * 2 - 1

    with torch.no_grad():
        raw_weights, global_bases = global_net(inputs)
        weights = raw_weights * 0.5 + 0.5
        weights = weights / (weights.sum(1, keepdim=True) + 1e-6)
        planes = global_bases[..., None, None].expand(-1, -1, -1, 256, 256)
        rendered = renderer._render((weights.unsqueeze(2) * planes).sum(1), light_dir, view_dir, distance).squeeze(1)
        error = rendered.clamp(0, 1) - photo
        deviations = local_net(torch.cat([inputs, error], 1), global_bases, weights)
        bases = deviations + planes
        normal, rest = bases.split(constants.NORMAL_AND_REFLECTANCE, 2)
        normal = normal / (normal.pow(2).sum(2, keepdim=True).sqrt() + 1e-12)
        bases = torch.cat([normal, rest], 2).clamp(-1, 1)
        maps = (weights.unsqueeze(2) * bases).sum(1)

    from mideepbasis.model.checkpoint import import_authors_weights, load_model
    from mideepbasis.model.inputs import lighting_mark

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        torch.save({"params": global_net.state_dict()}, folder / "net_g_2.414.pth")
        torch.save({"params": local_net.state_dict()}, folder / "net_l_2.414.pth")
        model = load_model(import_authors_weights(folder / "net_g_2.414.pth", folder / "net_l_2.414.pth", 45.0,
                                                  folder / "imported.safetensors"))
    light = torch.tensor([[0.0, 0.0, CAMERA_HEIGHT]])
    with torch.no_grad():
        ours = model(inputs, light)
    our_mark = lighting_mark(light, 256, 256, 45.0, "deepbasis", model.config.plane_extent)
    differences = {
        "lighting_mark": (our_mark - mark).abs().max(),
        "weights": (ours.weights - weights).abs().max(),
        "global_bases": (ours.global_bases - global_bases).abs().max(),
        "error_map": (ours.error - error).abs().max(),
        "local_deviations": (ours.deviations - deviations).abs().max(),
        "blended_maps_signed": (ours.signed_maps - maps).abs().max(),
    }
    report = {"authors_repo": str(args.authors_repo), "camera_height": CAMERA_HEIGHT, "input": "256x256, centred flash",
              "max_abs_difference": {k: float(v) for k, v in differences.items()},
              "map_value_range": [float(maps.min()), float(maps.max())]}
    for name, value in report["max_abs_difference"].items():
        print(f"{name:22s} {value:.3e}")
    write_report(args.output, "authors_equivalence", report)


if __name__ == "__main__":
    main()
