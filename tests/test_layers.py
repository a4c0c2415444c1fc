"""The package's layers (docs/ARCHITECTURE.md section 2): no module imports one of a higher layer,
imports inside functions included (read from the source, nothing imported)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mideepbasis"

#: Layers, bottom to top: the first part of a module's name below the package, by layer.
LAYERS = [
    {"constants", "errors", "startup", "configs"},
    {"geometry", "imageio", "resampling", "tiling", "material", "interchange", "outputs", "height"},
    {"render"},
    {"model"},
    {"data"},
    {"capturing"},
    {"export", "reporting", "viewer", "batch", "cluster"},
    {"evaluation"},
    {"train"},
    {"cli", "__init__", "__main__"},
]


def layer_of(part: str) -> int:
    for level, parts in enumerate(LAYERS):
        if part in parts:
            return level
    raise AssertionError(f"mideepbasis.{part} is in no layer of tests/test_layers.py: add it there and to "
                         "docs/ARCHITECTURE.md section 2")


def imported_parts(path: Path) -> set[str]:
    """The package's top-level parts that the module at ``path`` imports, anywhere in it."""
    module = path.relative_to(PACKAGE).with_suffix("").parts
    parts = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against the module's own package
                base = list(module[:-1])[: len(module) - node.level] if node.level > 1 else list(module[:-1])
                target = base + (node.module.split(".") if node.module else [])
                if not target:  # "from . import x" at the top: x itself
                    target = [alias.name for alias in node.names]
                parts.update([target[0]] if target else [])
            elif node.module and node.module.split(".")[0] == "mideepbasis" and "." in node.module:
                parts.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            parts.update(alias.name.split(".")[1] for alias in node.names
                         if alias.name.startswith("mideepbasis.") and alias.name.count(".") >= 1)
    return parts


def test_no_module_imports_from_a_higher_layer():
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        own = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        level = layer_of(own)
        for part in imported_parts(path):
            if part != own and layer_of(part) > level:
                upward.append(f"{path.relative_to(PACKAGE.parent)} imports mideepbasis.{part}")
    assert not upward, "\n".join(upward)


def test_the_check_sees_relative_imports_at_every_depth_and_inside_functions():
    assert {"errors", "render"} <= imported_parts(PACKAGE / "render" / "scenes.py")  # ..errors, .render's own
    assert {"constants", "material"} <= imported_parts(PACKAGE / "data" / "procedural" / "__init__.py")  # ...
    assert "render" in imported_parts(PACKAGE / "export.py")  # inside a function only
    assert "capturing" in imported_parts(PACKAGE / "evaluation" / "real.py")  # inside functions only
    assert layer_of("capturing") > layer_of("model") > layer_of("render")
