"""The check of a selected effect against what the fits did not use: the truth of a simulated
recording, or the reference sensors of a real one."""

from __future__ import annotations

from typing import Any

from flexforce.compare.diagnostics.fitting import Fit
from flexforce.compare.diagnostics.results import headline_errors
from flexforce.compare.metrics import evaluate


def reference_check(rec, base: Fit, fit: Fit, skip: float, known: dict) -> dict | None:
    """:attr:`Candidate.check` of ``fit`` against ``base`` (``known``: errors already computed, by
    the fits' sorted effects); None when the recording has nothing to check against or an
    evaluation fails.  With the F/T fused (``use_ft``) the errors against them are left out: the
    fit used them."""
    errs = []
    for f in (base, fit):
        key = tuple(sorted(f.effects))
        if key not in known:
            try:
                m = evaluate(f.estimate, rec, skip=skip)
            except Exception:  # a check is an aside: the diagnosis goes on without it
                return None
            known[key] = (getattr(m, "reference", None), headline_errors(m), dict(getattr(m, "references", {})))
        errs.append(known[key])
    (ref, before, refs), (_, after, _) = errs
    fused = bool(getattr(fit.model, "use_ft", False))  # --ft: the F/T are data of the fit, no check
    keep = {k: v for k, v in before.items() if v is not None and after.get(k) is not None
            and not (fused and refs.get(k) == "reference: F/T")}
    if not keep:
        return None
    out: dict[str, Any] = {"against": "truth" if ref == "truth" else "sensors", "before": keep,
                           "after": {k: after[k] for k in keep}}
    names = sorted({str(refs[k]).removeprefix("reference: ") for k in keep if k in refs and refs[k] != "truth"})
    if out["against"] == "sensors" and names:
        out["sensors"] = names
    return out
