"""The files socd ships: the DBCs, the example configs, the bundled cell profiles and the
bundled drive recording (``service/data``).

They live in the repository's top-level ``dbc/`` and ``configs/``; ``service/assets/dbc`` and
``service/assets/configs`` are symbolic links to those directories (as ``service/assets/results``
is to ``docs/results/``, whose markdown the help texts cite), so a source checkout, an
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
#: the measured results (``docs/results/*.md`` of the repository) the help texts cite
RESULTS_DIR_NAME = "results"
#: how a help text cites one of them
RESULTS_CITATION = "docs/results/"
#: the recordings shipped with the package, beside this package (``service/data``)
DATA_DIR = Path(__file__).resolve().parent.parent / "data"
#: recording names in the data directory that the demo takes for a drive cycle, in preference
DRIVE_NAME_HINTS = ("drive", "us06", "udds", "la92", "cycle")


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


def results_dir() -> Path:
    """Where the results a help text cites as ``docs/results/NAME.md`` are installed."""
    return asset_path(RESULTS_DIR_NAME)


def results_note() -> str:
    """The sentence that tells a user with only the installed package where ``docs/results/`` is."""
    return (f"{RESULTS_CITATION}NAME.md in a help text, where a default was measured, is installed "
            f"with socd: {results_dir()}/NAME.md")


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


def bundled_recordings() -> list[Path]:
    """The recordings (``*.csv``) shipped in ``service/data``."""
    return sorted(p for p in DATA_DIR.glob("*.csv") if not p.name.endswith("_truth.csv"))


def bundled_recording() -> Path:
    """The drive-cycle recording the demo replays: the first bundled recording named like a drive."""
    found = bundled_recordings()
    if not found:
        raise FileNotFoundError(f"no bundled recording (*.csv) in {DATA_DIR}")
    preferred = [p for p in found if any(k in p.name.lower() for k in DRIVE_NAME_HINTS)]
    return (preferred or found)[0]


def bundled_recording_named(name: str) -> Path | None:
    """The bundled recording called ``name`` (with or without ``.csv``), or None."""
    stem = name.removesuffix(".csv")
    return next((p for p in bundled_recordings() if p.stem == stem), None)


def bundled_recording_names() -> list[str]:
    """Names of the bundled recordings (commands that read recordings take them alone)."""
    return [p.stem for p in bundled_recordings()]


def missing_file_hint(what: str) -> str:
    """What socd ships in place of a ``what`` file that is not there ("recording", "cell profile"),
    for the end of the message that names it; empty for a kind socd ships none of."""
    if what == "recording" and (names := bundled_recording_names()):
        return f" (socd ships the recording {', '.join(names)}: give its name alone)"
    if what == "cell profile":
        return f" (bundled profiles, by name: {', '.join(bundled_profiles())})"
    return ""
