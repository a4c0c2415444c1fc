"""The draped cloth of the shape previews: a square sheet fallen over a ball, with folds.

    .venv/bin/python scripts/make_cloth_mesh.py [--resolution 96]

Writes scenes/meshes/cloth.ply (binary PLY: positions, normals, uv in [0, 1]^2 along the sheet's
own x and y). The sheet spans [-1.6, 1.6]^2 before draping; the ball has radius 0.9 and sits on
the plane z = 0; outside the ball the cloth falls to the floor in radial folds.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def drape(resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (V, 3), uv (V, 2), triangles (F, 3)) of the draped sheet."""
    u = np.linspace(0.0, 1.0, resolution)
    uu, vv = np.meshgrid(u, u, indexing="xy")
    x, y = (uu * 2 - 1) * 1.6, (vv * 2 - 1) * 1.6
    radius, angle = np.hypot(x, y), np.arctan2(y, x)
    ball = 0.9
    top = ball + np.sqrt(np.clip(ball**2 - radius**2, 0, None))  # over the ball: its upper half
    fall = np.clip((radius - 0.55) / 1.05, 0, 1)  # 0 over the ball's top, 1 at the sheet's edge
    height = np.where(radius < 0.55, top, ball + np.sqrt(ball**2 - 0.55**2) * (1 - fall) ** 2)
    folds = 0.12 * fall**1.5 * np.sin(7 * angle)
    spread = 1 + 0.15 * fall  # the cloth reaches out a little as it falls
    position = np.stack([x * spread + folds * np.cos(angle + math.pi / 2),
                         y * spread + folds * np.sin(angle + math.pi / 2), height + 0.02], axis=-1)
    index = np.arange(resolution * resolution).reshape(resolution, resolution)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    triangles = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return position.reshape(-1, 3), np.stack([uu, vv], -1).reshape(-1, 2), triangles


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    corners = positions[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(positions)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return normals * np.sign(normals[:, 2:3] + 1e-9)  # facing up, out of the cloth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "scenes/meshes/cloth.ply")
    args = parser.parse_args()
    positions, uv, triangles = drape(args.resolution)
    normals = vertex_normals(positions, triangles)
    header = "\n".join([
        "ply", "format binary_little_endian 1.0", "comment mideepbasis draped cloth (scripts/make_cloth_mesh.py)",
        f"element vertex {len(positions)}", "property float x", "property float y", "property float z",
        "property float nx", "property float ny", "property float nz", "property float u", "property float v",
        f"element face {len(triangles)}", "property list uchar int vertex_indices", "end_header"]) + "\n"
    vertices = np.concatenate([positions, normals, uv], axis=1).astype("<f4")
    faces = np.zeros(len(triangles), dtype=[("count", "u1"), ("index", "<i4", (3,))])
    faces["count"], faces["index"] = 3, triangles
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_bytes(header.encode() + vertices.tobytes() + faces.tobytes())
    print(f"wrote {args.output} ({len(positions)} vertices, {len(triangles)} triangles)")


if __name__ == "__main__":
    main()
