"""python-can's shared bus flags, so ``socd`` tools take the same ``-i/-c/-b/--fd`` as ``can.player``.

The flags are python-can's own (:func:`can.cli.add_bus_arguments`); :func:`resolve_bus` decides
which bus they, the socd config and python-can's own configuration describe, in this order
for each setting:

1. a command-line flag (``-i/--interface``, ``-c/--channel``, ``-b/--bitrate``, ``--fd``,
   ``--data-bitrate``, ``--timing``, ``--bus-kwargs``);
2. the user's socd config (``[bus]`` in the ``--config`` file, or ``SOCD_BUS__*``);
3. python-can's configuration (``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE`` and
   ``~/.canrc``/``/etc/can.conf``, read with :func:`can.util.load_config`);
4. the bundled default config (python-can's in-process ``virtual`` bus).

Without ``--config`` the bundled default's ``[bus]`` is a default (step 4), not the user's
choice, so ``CAN_INTERFACE=socketcan CAN_CHANNEL=vcan0 socd replay ...`` goes to vcan0.
An interface name python-can does not know is a :class:`BusConfigError` before anything opens.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from typing import Any

import can
import can.cli
from pydantic import ValidationError

from service.config import BusConfig, SocdConfig
from service.errors import validation_message

#: the command-line flag that sets each bus field (python-can's names)
_FLAG_NAMES = {"bitrate": "-b/--bitrate", "data_bitrate": "--data-bitrate", "fd": "--fd"}
#: namespace attributes python-can's flags set (absent when not given: argparse.SUPPRESS)
_FLAG_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing", "can_filters", "bus_kwargs")


class BusConfigError(ValueError):
    """The bus cannot be described (unknown interface, unusable python-can config)."""


def add_bus_arguments(parser: argparse.ArgumentParser, *, filter_arg: bool = False,
                      group_title: str | None = None) -> None:
    """python-can's ``-i/--interface -c/--channel -b/--bitrate --fd --data-bitrate --timing --bus-kwargs``.

    Flags not given are absent from the namespace, so the config and python-can's own
    configuration can fill them (see :func:`resolve_bus`).
    """
    can.cli.add_bus_arguments(parser, filter_arg=filter_arg, group_title=group_title)


def bus_flags_given(ns: argparse.Namespace) -> bool:
    """Whether ``-i`` or ``-c`` was given on the command line."""
    return "interface" in ns or "channel" in ns


@dataclass(frozen=True)
class ResolvedBus:
    """The bus to open and where its interface and channel came from."""

    bus: BusConfig
    interface_from: str
    channel_from: str

    def describe(self) -> str:
        origin = (self.interface_from if self.interface_from == self.channel_from
                  else f"interface from {self.interface_from}, channel from {self.channel_from}")
        return f"{self.bus.interface}:{self.bus.channel} ({origin})"

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus(**kwargs)``."""
        return self.bus.bus_kwargs()


def python_can_config(strict: bool = True) -> dict[str, Any]:
    """python-can's own bus configuration (environment, ``~/.canrc``, ...); ``{}`` when it has none.

    ``strict``: an interface name python-can does not know is a :class:`BusConfigError`
    (else python-can's configuration is ignored, for when its interface would not be used).
    """
    try:
        return dict(can.util.load_config())
    except can.CanInterfaceNotImplementedError:
        raw = {**can.util.load_file_config(), **can.util.load_environment_config()}
        name = raw.get("interface") or raw.get("bustype")
        if name and strict:
            raise BusConfigError(
                f"python-can configuration (CAN_INTERFACE or ~/.canrc): unknown interface {name!r}; "
                f"known: {', '.join(sorted(can.VALID_INTERFACES))}") from None
        return {}


def _user_set(config: SocdConfig | None, user_config: bool) -> set[str]:
    """``[bus]`` fields the user chose (file when it is theirs, or ``SOCD_BUS__*``)."""
    if config is None:
        return set()
    if user_config:
        return set(config.bus.model_fields_set)
    env = {k.upper() for k in os.environ}
    return {f for f in BusConfig.model_fields if f"SOCD_BUS__{f.upper()}" in env}


def check_interface(name: Any, where: str) -> None:
    if name not in can.VALID_INTERFACES:
        raise BusConfigError(f"{where}: unknown python-can interface {name!r}; "
                             f"known: {', '.join(sorted(can.VALID_INTERFACES))}")


def resolve_bus(ns: argparse.Namespace | None, config: SocdConfig, *, user_config: bool = True) -> ResolvedBus:
    """The bus that flags > the user's config > python-can's config > the bundled default describe.

    ``user_config``: the config came from the user (``--config``); False for the bundled
    default, whose ``[bus]`` then ranks below python-can's own configuration.
    """
    ns = ns if ns is not None else argparse.Namespace()
    flags = {k: getattr(ns, k) for k in _FLAG_KEYS if k in ns}
    chosen = _user_set(config, user_config)
    base = config.bus
    values: dict[str, Any] = base.model_dump()
    kwargs: dict[str, Any] = dict(base.kwargs)
    origin = {"interface": "config" if "interface" in chosen else "default",
              "channel": "config" if "channel" in chosen else "default"}

    decided = flags.keys() | chosen
    if not {"interface", "channel"} <= decided:
        pc = python_can_config(strict="interface" not in decided)
        pc.pop("bustype", None)
        pc_iface = pc.pop("interface", None)
        pc_channel = pc.pop("channel", None)
        if pc_iface and "interface" not in decided:
            if pc_iface != base.interface:
                kwargs = {}  # the bundled backend's settings do not apply to another backend
            values["interface"] = pc_iface
            origin["interface"] = "python-can config"
            for key in ("bitrate", "fd", "data_bitrate"):
                if key in pc and key not in chosen:
                    values[key] = pc.pop(key)
            kwargs.update({k: v for k, v in pc.items() if v is not None and k not in BusConfig.model_fields})
        final_iface = flags.get("interface", values["interface"])
        # python-can's channel belongs to python-can's interface
        if pc_channel is not None and "channel" not in decided and pc_iface == final_iface:
            values["channel"] = pc_channel
            origin["channel"] = "python-can config"

    if "interface" in flags:
        if flags["interface"] != values["interface"]:
            kwargs = {}  # a different backend: the config's backend-specific settings no longer apply
        values["interface"] = flags["interface"]
        origin["interface"] = "command line"
    if "channel" in flags:
        values["channel"] = flags["channel"]
        origin["channel"] = "command line"
    for key in ("bitrate", "fd", "data_bitrate"):
        if key in flags:
            values[key] = flags[key]
    for key in ("timing", "can_filters"):
        if key in flags:
            kwargs[key] = flags[key]
    kwargs.update(flags.get("bus_kwargs") or {})

    where = {"command line": "--interface", "config": "bus.interface",
             "python-can config": "python-can configuration (CAN_INTERFACE or ~/.canrc)",
             "default": "bus.interface"}[origin["interface"]]
    check_interface(values["interface"], where)
    values["kwargs"] = kwargs
    try:
        bus = BusConfig.model_validate(values)
    except ValidationError as exc:  # one line naming the flag or field, not pydantic's dump
        err = exc.errors()[0]
        key = str(err["loc"][0]) if err["loc"] else ""
        name = f"argument {_FLAG_NAMES[key]}" if key in flags and key in _FLAG_NAMES else f"bus.{key}"
        raise BusConfigError(f"bus settings: {name}: {validation_message(err)}, "
                             f"got {err.get('input')!r}") from None
    except ValueError as exc:
        raise BusConfigError(f"bus settings: {exc}") from None
    return ResolvedBus(bus, origin["interface"], origin["channel"])

