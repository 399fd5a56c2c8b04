"""Thresholds as measured values plus stated margins.

Every accuracy threshold of the suite is ``measured * (1 ± rel) ± add``, where ``measured`` is the
value recorded in ``tests/baseline.json`` under ``key`` and the margin is chosen, with its reason,
where the threshold is used.  The simulations are seeded, so a value is reproducible on one
machine; margins cover what legitimately moves it (floating-point summation order in other
BLAS/numba builds, where an iterative solver stops, a numerically equivalent rewrite), not an
estimator getting worse.

Measuring: with ``FLEXFORCE_BASELINE_RECORD=/path/values.jsonl`` every ``upper``/``lower`` call
appends ``{"key", "value"}`` to that file and the threshold becomes the value itself (the check
cannot fail while measuring).  ``python tests/baseline.py /path/values.jsonl`` then writes them into
``baseline.json``::

    FLEXFORCE_BASELINE_RECORD=/tmp/v.jsonl pytest -m "slow or not slow" && python tests/baseline.py /tmp/v.jsonl
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

BASELINE_FILE = Path(__file__).with_name("baseline.json")
_RECORD = os.environ.get("FLEXFORCE_BASELINE_RECORD")
_VALUES: dict[str, float] | None = None


def measured(key: str) -> float:
    """The value of ``key`` recorded in baseline.json."""
    global _VALUES
    if _VALUES is None:
        _VALUES = json.loads(BASELINE_FILE.read_text())["values"] if BASELINE_FILE.exists() else {}
    if key not in _VALUES:
        raise KeyError(f"no measured value for {key!r} in {BASELINE_FILE}; measure it (see tests/baseline.py)")
    return float(_VALUES[key])


def _record(key: str, value: float) -> bool:
    if not _RECORD:
        return False
    with open(_RECORD, "a") as f:
        f.write(json.dumps({"key": key, "value": float(value)}) + "\n")
    return True


def upper(key: str, value: float, *, rel: float = 0.0, add: float = 0.0) -> float:
    """Upper threshold for ``value``: its measured value times ``1 + rel``, plus ``add``."""
    if _record(key, value):
        return float(value)
    return measured(key) * (1.0 + rel) + add


def lower(key: str, value: float, *, rel: float = 0.0, add: float = 0.0) -> float:
    """Lower threshold for ``value``: its measured value times ``1 - rel``, minus ``add``."""
    if _record(key, value):
        return float(value)
    return measured(key) * (1.0 - rel) - add


def _merge(jsonl: Path) -> None:
    import platform

    import numpy as np

    data = json.loads(BASELINE_FILE.read_text()) if BASELINE_FILE.exists() else {"values": {}}
    data["about"] = ("Measured values behind the tests' thresholds (tests/baseline.py); the margin of each is "
                     "stated, with its reason, where the test uses it.")
    data["measured_with"] = {"python": platform.python_version(), "numpy": np.__version__,
                             "machine": platform.machine()}
    for line in jsonl.read_text().splitlines():
        item = json.loads(line)
        if not math.isfinite(item["value"]):
            raise ValueError(f"{item['key']}: measured {item['value']}")
        data["values"][item["key"]] = float(f"{item['value']:.6g}")
    data["values"] = dict(sorted(data["values"].items()))
    data = {k: data[k] for k in ("about", "measured_with", "values")}
    BASELINE_FILE.write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    _merge(Path(sys.argv[1]))
