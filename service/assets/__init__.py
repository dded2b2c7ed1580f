"""The files socd ships: the DBCs, the example configs and the bundled cell profiles.

They live in the repository's top-level ``dbc/`` and ``configs/``; ``service/assets/dbc`` and
``service/assets/configs`` are symbolic links to those directories, so a source checkout, an
editable install and a built wheel (which copies the files in) all find them here, through
:mod:`importlib.resources`, at the same relative places.  The example configs' relative paths
(``../dbc/bms_pack.dbc``, ``cells/panasonic_18650pf.toml``) therefore hold inside the package too.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: asset directories inside this package, by the config field whose packaged defaults they hold
DBC_DIR_NAME = "dbc"
CONFIG_DIR_NAME = "configs"
PROFILE_DIR_NAME = "cells"


def asset_path(*parts: str) -> Path:
    """A packaged file or directory as a file-system path (``asset_path("dbc", "bms_pack.dbc")``).

    socd installs as plain files (a wheel or a checkout), never zipped, so the resource is a
    real path that cantools and ``open`` can read directly.
    """
    resource = files(__name__).joinpath(*parts)
    if not isinstance(resource, Path):  # pragma: no cover - only a zipped install gets here
        raise RuntimeError(f"socd's packaged files must be on the file system, not in {resource}")
    return resource


def dbc_path(name: str) -> Path:
    """A packaged DBC, e.g. ``dbc_path("bms_pack.dbc")``."""
    return asset_path(DBC_DIR_NAME, name)


def config_path(name: str) -> Path:
    """A packaged example config, e.g. ``config_path("default.toml")``."""
    return asset_path(CONFIG_DIR_NAME, name)


def profile_path(name: str) -> Path:
    """A bundled cell profile, e.g. ``profile_path("panasonic_18650pf.toml")``."""
    return asset_path(CONFIG_DIR_NAME, PROFILE_DIR_NAME, name)


def bundled_profiles() -> list[str]:
    """Names of the bundled cell profiles (``--cell`` takes them without the suffix)."""
    return sorted(p.stem for p in asset_path(CONFIG_DIR_NAME, PROFILE_DIR_NAME).glob("*.toml"))


def example_configs() -> list[str]:
    """Names of the packaged example configs, relative to the configs directory."""
    root = asset_path(CONFIG_DIR_NAME)
    return sorted(
        str(p.relative_to(root)) for p in root.rglob("*.toml")
        if p.parent.name != PROFILE_DIR_NAME and "experiments" not in p.parts
    )
