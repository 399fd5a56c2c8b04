"""Shared test helpers."""

from __future__ import annotations

from pathlib import Path

# The real iCub recordings live in shared/, beside the checkout (../shared/data/icub).
ICUB_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "icub"
