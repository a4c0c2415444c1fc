"""mideepbasis: SVBRDF capture from one hand-held flash photograph (DeepBasis, SIGGRAPH Asia 2023)."""

from __future__ import annotations

__version__ = "0.1.0"
