"""Kept content held exactly: samples far from the sketches take the frozen base's field outputs.

SKED's L_pres holds kept content softly: the editable field is a copy of the base and is pulled
back towards it wherever the preservation weight w is high. Every step on the new part also moves
density and colour far from it (likely through hash entries shared between cells), which L_pres and
the photo anchor can only pull back afterwards: specks of new opacity across a capture's far field
The splat model holds its kept
Gaussians exactly; this is the same for a field: at a sample whose w exceeds `keep_threshold` the
edit *is* the base (outputs copied, no gradient), and the editable field is evaluated, and
trained, only at the others. `keep_threshold` 1 gives the paper's soft hold (w never exceeds 1).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import torch
from nerfstudio.cameras.rays import RaySamples
from torch import Tensor


def held_field_outputs(
    edit_field: Callable[[RaySamples], Dict],
    base_field: Callable[[RaySamples], Dict],
    ray_samples: RaySamples,
    kept: Optional[Tensor],
) -> Tuple[Dict, Dict]:
    """(composite outputs, base outputs) at every sample: the base's where `kept`, the edit's elsewhere.

    `kept` has the samples' shape (None: nothing held, the edit everywhere). Both fields are evaluated at every
    sample, the base without gradients (L_pres compares the two there), and the composite picks per sample without
    looking at `kept` on the host: no sync and no data-dependent shape, so a step launches the same kernels whatever
    the sketches hold. A kept sample's edit output gets no gradient. The fields map RaySamples of any batch shape to
    a dict of (*shape, channels) tensors, as nerfstudio's fields do.
    """
    with torch.no_grad():
        base = base_field(ray_samples)
    return hold(edit_field(ray_samples), base, kept), base


def hold(edited: Dict, base: Dict, kept: Optional[Tensor]) -> Dict:
    """The edit's outputs with the base's at `kept` samples (None: none), picked per sample with no host sync."""
    if kept is None:
        return edited
    held = kept[..., None]
    return {key: torch.where(held, base[key].detach().to(value.dtype), value) for key, value in edited.items()}
