"""Paths of the assets bundled with the package (default cell profile, demo drive)."""

from __future__ import annotations

from pathlib import Path

REPO_CONFIGS = Path(__file__).resolve().parents[2] / "configs"
PACKAGE_DATA = Path(__file__).resolve().parents[1] / "data"


def default_profile_path() -> Path:
    """The bundled Panasonic 18650PF profile (package data, else the repo's configs/)."""
    for p in (PACKAGE_DATA / "panasonic_18650pf.toml", REPO_CONFIGS / "cells" / "panasonic_18650pf.toml"):
        if p.is_file():
            return p
    return REPO_CONFIGS / "cells" / "panasonic_18650pf.toml"
