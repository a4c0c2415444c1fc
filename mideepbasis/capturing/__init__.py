"""Photo to material: load the photo, find the flash, predict the bases, refine the global bases.

    from mideepbasis import capture
    result = capture("flash_photo.jpg")                   # a CaptureResult
    result.material.save("out/")

Stages (docs/ARCHITECTURE.md section 10), one module each, run by the engine in ``pipeline`` (``Capturer``):

1. **Photo** (``photo``): read, EXIF field of view, crop, centre square, working resolution.
2. **Lighting search** (``search``): the flash position of a hand-held shot.
3. **Prediction** (``pipeline.predict_small``) with the found light: weights, global bases, local
   deviations, kept at the network's resolution (a ``Prediction``).
4. **Refinement** (``refine``): the global bases fitted to the photo by differentiable rendering.
5. **Blend** (``Prediction.maps``): the maps at the photo's size, one basis at a time.

Shapes: photos (B, 3, H, W) linear in [0, 1]; lights (B, 3) flash positions and offsets (B, 2)
[patch half-widths].
"""

from __future__ import annotations

from .photo import MAX_NATIVE_RESOLUTION, MIN_PHOTO_SIZE, field_of_view_from_focal, load_photo
from .pipeline import (CaptureConfig, CaptureResult, Capturer, Photo, Prediction, capture, network_resolution_limit,
                       predict, predict_small)
from .refine import RefineConfig, SmallAdam, refine_global_bases
from .search import SearchConfig, SearchResult, candidate_offsets, light_objective, search_light

__all__ = ["MAX_NATIVE_RESOLUTION", "MIN_PHOTO_SIZE", "CaptureConfig", "CaptureResult", "Capturer", "Photo",
           "Prediction", "RefineConfig", "SearchConfig", "SearchResult", "SmallAdam", "candidate_offsets", "capture",
           "field_of_view_from_focal", "light_objective", "load_photo", "network_resolution_limit", "predict",
           "predict_small", "refine_global_bases", "search_light"]
