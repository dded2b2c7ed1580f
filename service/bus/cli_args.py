"""python-can's shared bus flags, so ``socd`` tools take the same ``-i/-c/-b`` as ``can.player``.

Thin wrappers over :mod:`can.cli` (python-can ≥ 4.5 ships ``add_bus_arguments`` and
``create_bus_from_namespace``; we reuse them rather than re-implement), plus a fallback
to a :class:`~service.config.SocdConfig`'s ``[bus]`` section for flags not given.
"""

from __future__ import annotations

import argparse
from typing import Any

import can
import can.cli

from service.config import SocdConfig

_BUS_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing", "can_filters", "bus_kwargs")


def add_bus_arguments(parser: argparse.ArgumentParser, *, filter_arg: bool = False,
                      group_title: str | None = None) -> None:
    """Add ``-i/--interface -c/--channel -b/--bitrate --fd --data-bitrate --timing --bus-kwargs``.

    Flags not given are absent from the namespace (``argparse.SUPPRESS``), so a config
    file's ``[bus]`` section can fill them (see :func:`create_bus_from_namespace`).
    """
    can.cli.add_bus_arguments(parser, filter_arg=filter_arg, group_title=group_title)


def bus_kwargs_from_namespace(ns: argparse.Namespace, config: SocdConfig | None = None) -> dict[str, Any]:
    """``can.Bus`` keyword arguments: command-line flags first, then ``config.bus``."""
    kw: dict[str, Any] = dict(config.bus.bus_kwargs()) if config is not None else {}
    given = {k: getattr(ns, k) for k in _BUS_KEYS if k in ns}
    if "interface" in given and config is not None and given["interface"] != config.bus.interface:
        # a different backend: the config's backend-specific settings no longer apply
        kw = {}
    extra = given.pop("bus_kwargs", None) or {}
    kw.update(given)
    kw.update(extra)
    if kw.get("interface") == "virtual":
        kw.pop("bitrate", None)
    return kw


def create_bus_from_namespace(ns: argparse.Namespace, config: SocdConfig | None = None,
                              **kwargs: Any) -> can.BusABC:
    """Open the bus the flags (else ``config.bus``) describe.

    Without a config this is exactly :func:`can.cli.create_bus_from_namespace` (which falls
    back to python-can's own config files / ``CAN_*`` environment for missing flags).
    """
    if config is None:
        return can.cli.create_bus_from_namespace(ns, **kwargs)
    kw = bus_kwargs_from_namespace(ns, config)
    kw.update(kwargs)
    return can.Bus(**kw)
