"""STDR's side of the compact file's protocol (stdr.compression.hooks): how the file stores the
mask (its 8-bit form, or the separated field's output in its place) and what of the plug-in's
state a render needs. A mixin of the plug-in class (stdr.plugins.stdr.plugin.STDR)."""
from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ...compression.hooks import CompactForm
from .mask import COND_KEY, MASK_KEY, activated
from .phases import Phase


class CompactMask:
    """compact_fallback, check_compact_spec and compact_form of the STDR plug-in; it reads the
    plug-in's has_mask, phase, mask_modulates, field and conditioning."""

    compact_fallback = {MASK_KEY: "q8"}  # the 8-bit mask: exact for a run with stdr.mask_bits=8

    @classmethod
    def check_compact_spec(cls, pcfg, spec: dict) -> None:
        """stdr_mask=derived needs a run whose mask stops multiplying opacity at the freeze and whose
        separated field is on (compact_form)."""
        if spec.get(MASK_KEY) != "derived":
            return
        if pcfg.mask_after_freeze or not pcfg.separated_field or not pcfg.mask:
            raise ValueError(f"{MASK_KEY}=derived stores the separated field's output in place of the mask, "
                             "which needs stdr.mask_after_freeze=false, stdr.separated_field=true and stdr.mask=true "
                             f"in this run (here {pcfg.mask_after_freeze=}, {pcfg.separated_field=}, {pcfg.mask=}); "
                             f"set them, or store the mask itself ({MASK_KEY}=q8)")

    def compact_form(self, params, state: dict[str, Any], step: int, derive: set[str]) -> CompactForm:
        """units: the mask, read by renders as activated(m) and by the field as logits_of(m); both
        read an 8-bit mask (stdr.mask_bits=8) as well as float logits. derived (when `derive` names
        the mask): the separated field's output cond = [z, d] [N, cond_dim] in its place. Past the
        freeze, with `stdr.mask_after_freeze=false`, a finished model reads the mask only through
        the field (p = softmax_t(m) -> z, d), whose output is the same at every time, so the file
        stores cond (cond_dim numbers a Gaussian instead of K) and no field weights. state: a
        render reads neither the spatial regularizer's neighbour cache nor its random generator
        (training state: 48 KB at 10,000 rows), so the file keeps neither."""
        if not self.has_mask(params):
            return CompactForm(state={**state, "knn": None, "knn_valid": False, "gen": None})
        units = {MASK_KEY: activated(params[MASK_KEY].detach()).float()}
        derived = {MASK_KEY: (COND_KEY, self._derived_mask(params, step))} if MASK_KEY in derive else {}
        out = {**state, "knn": None, "knn_valid": False, "gen": None}
        return CompactForm(units, derived, {**out, "field": None} if derived else out)

    def _derived_mask(self, params, step: int) -> Tensor:
        """The separated field's output at `step`, or a ValueError saying why this model cannot
        store its mask that way."""
        # the phase first: before the freeze the mask modulates opacity whatever mask_after_freeze says
        why = ("the model is not past the freeze" if self.phase(step) != Phase.FROZEN else
               "the mask still multiplies opacity at this step (stdr.mask_after_freeze=true)"
               if self.mask_modulates(step) else
               "the separated field is off (stdr.separated_field=false)" if self.field is None else "")
        if why:
            raise ValueError(f"compact spec {MASK_KEY}=derived stores the separated field's output in place of "
                             f"the mask, which needs a model past the freeze whose mask no longer multiplies "
                             f"opacity and whose field is on; here {why}. Store the mask itself "
                             f"({MASK_KEY}=q8, the 8-bit mask) or train with stdr.mask_after_freeze=false")
        was = self.field.training
        self.field.eval()
        try:
            with torch.no_grad():
                cond, _ = self.conditioning_at(params, step)
        finally:
            self.field.train(was)
        return cond.detach().float()
