"""Optional parts of socd and the pip extra that installs each (``[project.optional-dependencies]``).

The daemon needs none of them; ``socd fit``/``evaluate``/``diagnose`` need ``fit``, MF4 logs
need ``mf4``.  A command that meets a missing one says, in one line, which extra to install.
"""

from __future__ import annotations

import importlib.util

#: top-level module -> the extra of pyproject.toml that installs it
EXTRA_OF_MODULE: dict[str, str] = {
    "scipy": "fit",
    "matplotlib": "fit",
    "tomli_w": "fit",
    "asammdf": "mf4",
    "pybamm": "research",
}


def installed(module: str) -> bool:
    """Whether ``module`` (top level) can be imported, without importing it."""
    return importlib.util.find_spec(module) is not None


def install_hint(module: str) -> str:
    """``needs scipy: pip install 'socd[fit]'`` for a module an extra provides."""
    return f"needs {module}, which is not installed: pip install 'socd[{EXTRA_OF_MODULE[module]}]'"


def missing_extra(exc: BaseException) -> str | None:
    """:func:`install_hint` for an import error of a module an extra provides, else ``None``."""
    if isinstance(exc, ModuleNotFoundError) and exc.name:
        module = exc.name.partition(".")[0]
        if module in EXTRA_OF_MODULE:
            return install_hint(module)
    return None
