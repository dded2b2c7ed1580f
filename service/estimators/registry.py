"""Estimators by name, as ``socd evaluate --estimator NAME`` knows them.

A plain dict of factories (python-can's ``BACKENDS`` style): adding an estimator is one
line here.  Each factory takes the pipeline settings (baselines ignore them).
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable

from service.estimators.base import Estimator
from service.estimators.settings import EstimatorSettings

#: name -> ("module", "factory"); the factory is called with ``settings=``
ESTIMATORS: dict[str, tuple[str, str]] = {
    "fomiukf": ("service.estimators.pipeline", "fomiukf"),
    "foukf": ("service.estimators.pipeline", "foukf"),
    "fom-single-scale": ("service.estimators.pipeline", "fom_single_scale"),
    "ecm2rc-ekf": ("service.estimators.ecm2rc_ekf", "Ecm2RcEkf"),
    "huwang-rls": ("service.estimators.huwang_rls", "HuWangRls"),
    "coulomb": ("service.estimators.coulomb", "CoulombCounter"),
}


class UnknownEstimator(ValueError):
    pass


def create(name: str, settings: EstimatorSettings | None = None, options: dict | None = None) -> Estimator:
    """``settings`` go to the paper's pipeline variants, ``options`` (keyword arguments) to a
    baseline's factory, e.g. the 2-RC EKF's EkfTuning fields."""
    if name not in ESTIMATORS:
        close = difflib.get_close_matches(name, ESTIMATORS, n=3)
        hint = f" Best matches: {', '.join(close)}." if close else ""
        raise UnknownEstimator(f"estimator '{name}' not recognised; known: {', '.join(ESTIMATORS)}.{hint}")
    module_name, attr = ESTIMATORS[name]
    factory: Callable[..., Estimator] = getattr(importlib.import_module(module_name), attr)
    if module_name.endswith("pipeline"):
        return factory(settings)
    return factory(**(options or {}))
