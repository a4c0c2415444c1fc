"""mideepbasis: SVBRDF capture from one hand-held flash photograph (DeepBasis, SIGGRAPH Asia 2023)."""

from __future__ import annotations

import os

# torch's OpenMP workers spin after every parallel region by default; drjit's LLVM kernels then
# share the cores with spinning threads, which doubles the time of a render between two torch
# ops on a small machine. Passive waiting frees the cores at once (a user's own setting wins).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
