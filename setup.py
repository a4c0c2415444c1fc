"""The package list, which pyproject.toml alone cannot give: every package under mideepbasis/,
found, and the scenes, which live at the top of the repository (docs/ARCHITECTURE.md section 2)
and install inside the package as mideepbasis.scenes. Everything else is in pyproject.toml."""

from setuptools import find_packages, setup

setup(packages=find_packages(include=["mideepbasis", "mideepbasis.*"]) + ["mideepbasis.scenes"],
      package_dir={"mideepbasis.scenes": "scenes"})
