"""The service configuration: one TOML file, overridable from the environment.

Layering (python-can style): the file, then ``SOCD_*`` environment variables (nested with
``__``, e.g. ``SOCD_BUS__CHANNEL=can0``, ``SOCD_ESTIMATOR__MEMORY_LENGTH=32``); the
environment wins.  Every section forbids unknown keys, so a typo is an error, and every
error names the file and the field (``configs/x.toml: mapping.cell_voltage_signals[3]:
...``).

Which signal is the pack current, which are cell voltages (and which cell each is) and
which are temperatures (and which cells each covers) is configuration, not code
(DESIGN §4): a user's own DBC works by editing ``[mapping]`` only.  Cell indices are
0-based everywhere in the config.

Relative paths in the file resolve against the file's directory; relative paths from the
environment resolve against the working directory.  A relative DBC or cell-profile path that
names no file there falls back to the file of that name that socd ships
(:mod:`service.assets`), so an example config copied to ``/etc/socd/`` still finds
``bms_pack.dbc``; ``--config`` itself falls back the same way to a packaged example config.
"""

from __future__ import annotations

import difflib
import functools
import logging
import math
import os
import re
import string
import tomllib
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from service.assets import config_path, dbc_path, example_configs, profile_path
from service.errors import UserError, validation_message
from service.estimators.settings import EstimatorSettings
from service.strict_numbers import NoBooleanNumbers
from service.validation import RecordingBounds

log = logging.getLogger(__name__)
#: environment variables with this prefix override the config file (nested with ``__``)
ENV_PREFIX = "SOCD_"
#: nests an override into a section: SOCD_BUS__CHANNEL sets [bus] channel
ENV_NESTED_DELIMITER = "__"

DEFAULT_INPUT_DBC = dbc_path("bms_pack.dbc")
DEFAULT_OUTPUT_DBC = dbc_path("socd_output.dbc")
DEFAULT_CELL_PROFILE = profile_path("panasonic_18650pf.toml")
DEFAULT_CONFIG = config_path("default.toml")
#: file name of the checkpoint when the config gives no ``[checkpoint] path``
CHECKPOINT_FILE_NAME = "socd-state.npz"

#: messages/signals the encoder needs in ``dbc.output``
OUTPUT_MESSAGES: dict[str, tuple[str, ...]] = {
    "SOCD_CellSoc": ("SOCD_SocCellIndex", "SOCD_Soc", "SOCD_SocStd"),
    "SOCD_CellParams": ("SOCD_ParCellIndex", "SOCD_ROhm", "SOCD_RCt", "SOCD_RDf", "SOCD_M", "SOCD_N"),
    "SOCD_PackSummary": ("SOCD_SocMin", "SOCD_SocMean", "SOCD_SocMax", "SOCD_SocMinCell", "SOCD_SocMaxCell"),
    "SOCD_Status": ("SOCD_FramesRejected", "SOCD_StaleCells"),
}


class ConfigError(UserError):
    """A configuration that cannot be used; the message is ``<file>: <field.path>: <msg>``.  A
    :class:`UserError`, so a command that builds a config without catching it (``demo``,
    ``bench --latency``: a bad ``SOCD_*`` override) still exits 2 with the message."""


class _Section(NoBooleanNumbers, BaseModel):
    # a NaN or infinite setting (a period, a scale, a noise level) is a mistake, never a value
    model_config = ConfigDict(extra="forbid", validate_assignment=False, allow_inf_nan=False)


# ---------------------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------------------
class BusConfig(_Section):
    """The CAN bus, as python-can's ``can.Bus(interface=..., channel=..., ...)``."""

    interface: str = "virtual"
    channel: str | int = "vcan0"
    bitrate: int | None = Field(500000, gt=0)
    fd: bool = False
    data_bitrate: int | None = Field(None, gt=0)
    receive_own_messages: bool = False
    reconnect_initial_s: float = Field(0.5, gt=0)
    reconnect_max_s: float = Field(10.0, gt=0)
    max_open_retries: int = Field(
        10, ge=0,
        description="failed bus opens at start-up after which 'socd run' gives up with exit status 1 "
        "(each retry waits reconnect_initial_s, doubling up to reconnect_max_s); 0 = retry for ever. "
        "Once the bus has opened, a link that goes down later is reopened for as long as it takes",
    )
    kwargs: dict[str, Any] = Field(
        default_factory=dict,
        description="extra can.Bus keyword arguments, like python-can's --bus-kwargs "
        "(e.g. preserve_timestamps = true on a virtual bus)",
    )

    @model_validator(mode="after")
    def _backoff(self) -> BusConfig:
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError(
                f"reconnect_max_s ({self.reconnect_max_s}) < reconnect_initial_s ({self.reconnect_initial_s})"
            )
        return self

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus(**kwargs)``."""
        kw: dict[str, Any] = {
            "interface": self.interface,
            "channel": self.channel,
            "receive_own_messages": self.receive_own_messages,
        }
        if self.bitrate is not None and self.interface != "virtual":
            kw["bitrate"] = self.bitrate
        if self.fd:
            kw["fd"] = True
            if self.data_bitrate is not None:
                kw["data_bitrate"] = self.data_bitrate
        kw.update(self.kwargs)
        return kw


def special_file_problem(path: Path) -> str | None:
    """Why ``path`` cannot be one of the config's files, or None: it exists but is no regular file
    (a named pipe blocks whoever opens it for reading; a device such as ``/dev/null`` would be
    replaced by the first checkpoint written). A missing file is each field's own check."""
    if path.exists() and not path.is_dir() and not path.is_file():
        return f"{path} is a device, named pipe or socket, not a regular file"
    return None


def _regular_file(v: Path | None) -> Path | None:
    if v is not None and (problem := special_file_problem(v)) is not None:
        raise ValueError(problem)
    return v


class DbcConfig(_Section):
    input: Path = DEFAULT_INPUT_DBC
    output: Path = DEFAULT_OUTPUT_DBC

    _files = field_validator("input", "output")(_regular_file)


class CellVoltageMap(_Section):
    """One cell voltage signal and the (0-based) cell it measures."""

    cell: int = Field(ge=0)
    signal: str = Field(min_length=1)


class TemperatureMap(_Section):
    """One temperature signal and the (0-based) cells it covers."""

    signal: str = Field(min_length=1)
    cells: list[int] = Field(min_length=1)


#: the values a cell's voltage and temperature can physically take, per ``[mapping]`` plausibility
#: range (the recording loaders' bounds): a range wholly outside them counts every value of every
#: frame as ``out_of_range`` (service.bus.decoder)
PHYSICAL_SPANS: dict[str, tuple[float, float, str, str]] = {
    "voltage_range_v": (*RecordingBounds.voltage_v, "V", "a cell's voltage"),
    "temperature_range_c": (*RecordingBounds.temperature_c, "°C", "a cell's temperature"),
}


def range_problem(field: str, v: tuple[float, float]) -> str | None:
    """Why the ``[mapping]`` plausibility range ``field`` = ``v`` would reject every value the
    decoder reads, or None: not low < high, wholly outside what a cell can read
    (:data:`PHYSICAL_SPANS`), or, for the current, leaving out 0 A (a pack at rest)."""
    lo, hi = v
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        return f"must be [low, high] with low < high, got {list(v)}"
    if field in PHYSICAL_SPANS:
        span_lo, span_hi, unit, what = PHYSICAL_SPANS[field]
        if hi <= span_lo or lo >= span_hi:
            return (f"{list(v)} lies wholly outside {span_lo:g} to {span_hi:g} {unit}, where {what} lies: "
                    "every value would be rejected (out_of_range)")
    elif not lo <= 0.0 <= hi:
        return (f"{list(v)} leaves out 0 A: the current of a pack at rest would be rejected (out_of_range), "
                "and a rejected current gives no sample")
    return None


#: the widest field a signal-name pattern may format (``{number:03d}`` is 3)
MAX_PATTERN_WIDTH = 16


class MappingConfig(_Section):
    """Which DBC signals feed the estimator.

    Cell voltages, one of: ``cell_voltage_signals`` (index i = cell i), ``cells``
    (``[{cell, signal}]``) or ``cell_voltage_pattern`` (``str.format`` with ``index``
    = 0-based and ``number`` = 1-based cell, expanded to ``pack.n_cells`` names).
    Temperatures, one of: ``temperature_signals`` (``[{signal, cells}]``) or
    ``temperature_pattern`` + ``cells_per_sensor`` (sensor k covers cells
    ``k*cps .. k*cps+cps-1``; ``index``/``number`` as above, for the sensor).
    After validation ``cell_voltage_signals`` and ``temperature_signals`` are always filled.
    """

    current_signal: str = "BMS_PackCurrent"
    current_sign: float = Field(-1.0, description="decoded × sign × scale = current, positive = discharge")
    current_scale: float = Field(1.0, gt=0)
    cell_voltage_signals: list[str] = []
    cells: list[CellVoltageMap] = []
    cell_voltage_pattern: str | None = "BMS_Cell{number:03d}_V"
    temperature_signals: list[TemperatureMap] = []
    temperature_pattern: str | None = "BMS_Temp{number:02d}_C"
    cells_per_sensor: int | None = Field(4, ge=1)
    counter_signals: dict[str, str] = {
        "BMS_PackStatus": "BMS_PackCounter",
        "BMS_CellVoltages": "BMS_CellVoltCounter",
        "BMS_CellTemps": "BMS_CellTempCounter",
    }
    voltage_range_v: tuple[float, float] = (1.5, 4.8)
    temperature_range_c: tuple[float, float] = (-40.0, 90.0)
    current_range_a: tuple[float, float] = (-1000.0, 1000.0)
    stale_after_s: float = Field(2.0, gt=0)
    max_clock_jump_s: float = Field(
        10.0, gt=0, description="a frame further than this from its ID's timeline is rejected; "
        "a run of agreeing ones re-anchors the ID (service.bus.decoder)")
    time_signal: str | None = Field(
        None, min_length=1, description="a signal carrying the sender's sample time in seconds "
        "(BMS_SampleTime in the shipped DBC), sent once per sample before the sample's other frames: "
        "samples are then clocked by it instead of by frame arrival, so a replay faster than real "
        "time onto a kernel bus keeps the recording's time steps (service.bus.timesync). "
        "None: frame timestamps")

    @field_validator("current_sign")
    @classmethod
    def _sign(cls, v: float) -> float:
        if v not in (-1.0, 1.0):
            raise ValueError("must be 1 or -1 (use current_scale for scaling)")
        return v

    @field_validator("voltage_range_v", "temperature_range_c", "current_range_a")
    @classmethod
    def _range(cls, v: tuple[float, float], info: ValidationInfo) -> tuple[float, float]:
        if (problem := range_problem(str(info.field_name), v)) is not None:
            raise ValueError(problem)
        return v

    @field_validator("cell_voltage_pattern", "temperature_pattern")
    @classmethod
    def _pattern(cls, v: str | None) -> str | None:
        if v is not None:
            try:
                # a field width like {number:0999999999d} would build a gigabyte per name
                specs = [spec for _, _, spec, _ in string.Formatter().parse(v) if spec]
                # a width read from a field ({number:0{number}{number}d}) grows with the cell number
                if any("{" in spec for spec in specs):
                    raise ValueError("a format spec that holds a field of its own")
                widths = [int(d) for spec in specs for d in re.findall(r"\d+", spec)]
                if any(w > MAX_PATTERN_WIDTH for w in widths):
                    raise ValueError(f"a field width over {MAX_PATTERN_WIDTH}")
                a, b = v.format(index=0, number=1), v.format(index=1, number=2)
            except (KeyError, IndexError, ValueError) as exc:
                raise ValueError(f"pattern {v!r} must use only {{index}} and/or {{number}}: {exc}") from None
            if a == b:
                raise ValueError(f"pattern {v!r} gives the same name for every cell")
        return v

    def expand(self, n_cells: int) -> None:
        """Fill ``cell_voltage_signals`` / ``temperature_signals`` from the compact forms.

        Explicitly given forms must agree with each other (so a dumped, already expanded
        config validates again); the pattern defaults apply only when no form was given.
        """
        set_ = self.model_fields_set
        candidates: list[tuple[str, list[str]]] = []
        if self.cell_voltage_signals:
            candidates.append(("cell_voltage_signals", list(self.cell_voltage_signals)))
        if self.cells:
            seen: dict[int, str] = {}
            for k, c in enumerate(self.cells):
                if c.cell in seen:
                    raise ValueError(f"mapping.cells[{k}].cell: cell {c.cell} is mapped twice")
                if c.cell >= n_cells:
                    raise ValueError(f"mapping.cells[{k}].cell: {c.cell} >= pack.n_cells ({n_cells})")
                seen[c.cell] = c.signal
            missing = [i for i in range(n_cells) if i not in seen]
            if missing:
                raise ValueError(f"mapping.cells: no signal for cell(s) {missing[:10]}")
            candidates.append(("cells", [seen[i] for i in range(n_cells)]))
        if self.cell_voltage_pattern is not None and ("cell_voltage_pattern" in set_ or not candidates):
            candidates.append(("cell_voltage_pattern", [
                self.cell_voltage_pattern.format(index=i, number=i + 1) for i in range(n_cells)
            ]))
        if not candidates:
            raise ValueError("mapping: give one of cell_voltage_signals, cells, cell_voltage_pattern")
        for name, lst in candidates[1:]:
            if lst != candidates[0][1]:
                raise ValueError(f"mapping.{name}: conflicts with mapping.{candidates[0][0]}; give only one")
        self.cell_voltage_signals = candidates[0][1]

        t_candidates: list[tuple[str, list[TemperatureMap]]] = []
        if self.temperature_signals:
            t_candidates.append(("temperature_signals", list(self.temperature_signals)))
        if self.temperature_pattern is not None and ("temperature_pattern" in set_ or not t_candidates):
            if self.cells_per_sensor is None:
                raise ValueError("mapping.cells_per_sensor: required with temperature_pattern")
            cps = self.cells_per_sensor
            t_candidates.append(("temperature_pattern", [
                TemperatureMap(
                    signal=self.temperature_pattern.format(index=k, number=k + 1),
                    cells=list(range(k * cps, min(n_cells, (k + 1) * cps))),
                )
                for k in range(math.ceil(n_cells / cps))
            ]))
        if not t_candidates:
            raise ValueError("mapping: give one of temperature_signals, temperature_pattern")
        for name, lst in t_candidates[1:]:
            if lst != t_candidates[0][1]:
                raise ValueError(f"mapping.{name}: conflicts with mapping.{t_candidates[0][0]}; give only one")
        self.temperature_signals = t_candidates[0][1]

    def sensor_of_cell(self, n_cells: int) -> list[int]:
        """Index into ``temperature_signals`` of the (first) sensor covering each cell."""
        out = [-1] * n_cells
        for k, t in enumerate(self.temperature_signals):
            for c in t.cells:
                if 0 <= c < n_cells and out[c] < 0:
                    out[c] = k
        return out

    def all_signals(self) -> list[tuple[str, str]]:
        """``(field path, signal name)`` of every mapped input signal."""
        out = [("mapping.current_signal", self.current_signal)]
        out += [(f"mapping.cell_voltage_signals[{i}]", s) for i, s in enumerate(self.cell_voltage_signals)]
        out += [(f"mapping.temperature_signals[{k}].signal", t.signal) for k, t in enumerate(self.temperature_signals)]
        out += [(f"mapping.counter_signals.{m}", s) for m, s in self.counter_signals.items()]
        if self.time_signal is not None:
            out.append(("mapping.time_signal", self.time_signal))
        return out


#: s: the shortest publication period taken; at 1e-9 s the publishing loop spun a core at 100 % doing nothing
MIN_PUBLISH_PERIOD_S = 0.001


class OutputConfig(_Section):
    can_enabled: bool = True
    can_period_s: float = Field(1.0, ge=MIN_PUBLISH_PERIOD_S)
    zenoh_enabled: bool = True
    zenoh_period_s: float = Field(0.5, ge=MIN_PUBLISH_PERIOD_S,
                                  description="period of the full Zenoh round: every cell's parameters, health, "
                                  "and the SOC keys no estimate refreshed since the last one")
    min_publish_interval_s: float = Field(0.05, ge=0, description="no Zenoh key is put more often than this; "
                                          "SOC and summary go out when estimated, held back only by it (0 = never)")
    queue_size: int = Field(256, ge=1)


def endpoint_problem(e: str) -> str | None:
    """Why ``e`` is not a Zenoh endpoint ``<protocol>/<address>`` with a port in 0..65535
    (``tcp/127.0.0.1:7447``), or None."""
    proto, _, address = e.partition("/")
    if not proto or not address or not proto.replace("-", "").isalnum():
        return f"{e!r} is not a Zenoh endpoint (<protocol>/<address>, e.g. tcp/127.0.0.1:7447)"
    if proto not in LINK_PROTOCOLS:
        return f"{e!r}: Zenoh has no link protocol {proto!r} ({', '.join(LINK_PROTOCOLS)})"
    host, sep, port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    if proto in PORTED_PROTOCOLS and not (sep and port.isdigit()):
        return f"{e!r}: a {proto} endpoint needs a numeric port (<host>:<port>, e.g. tcp/127.0.0.1:7447)"
    if proto in PORTED_PROTOCOLS and not host:
        return f"{e!r}: a {proto} endpoint needs a host before the port (e.g. tcp/127.0.0.1:7447, tcp/[::]:7447)"
    if sep and port.isdigit() and int(port) > 65535:
        return f"{e!r}: port {port} is outside 0..65535"
    return None


#: Zenoh link protocols addressed by host and port (Zenoh failed on a bad port with "invalid port
#: value" at every retry, naming neither the endpoint nor the field)
PORTED_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
#: every link protocol Zenoh has (an unknown one failed at each reconnect with "Unicast not supported")
LINK_PROTOCOLS = (*PORTED_PROTOCOLS, "unixsock-stream", "unixpipe", "serial", "vsock")


def key_chunk_problem(v: str) -> str | None:
    """Why ``v`` cannot be part of a Zenoh key expression (a prefix or a pack id), or None: no
    wildcards, no empty chunk, no leading or trailing slash."""
    if not v or set(v) & set("*$?#") or v.startswith("/") or v.endswith("/") or "//" in v:
        return f"{v!r} is not a valid key-expression part (no wildcards, no empty or leading/trailing '/')"
    return None


class ZenohConfig(_Section):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = ["tcp/127.0.0.1:7447"]
    connect: list[str] = []
    scouting_multicast: bool = False
    key_prefix: str = Field("bms", min_length=1)
    pack_id: str = Field("pack0", min_length=1)
    config_file: Path | None = Field(
        None,
        description="a Zenoh JSON5 config file (zenoh.Config.from_file: TLS, auth, routers, ...). "
        "Precedence: a key the file sets wins; mode, listen/endpoints, connect/endpoints and "
        "scouting/multicast/enabled from this section are applied only where the file leaves "
        "them at Zenoh's default. Relative paths resolve against the socd config file's directory.",
    )

    _file = field_validator("config_file")(_regular_file)

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        """Checked here so ``socd check`` names a bad endpoint instead of the session failing when
        ``socd run`` opens it (:func:`endpoint_problem`)."""
        for e in v:
            if (problem := endpoint_problem(e)) is not None:
                raise ValueError(problem)
        return v

    @field_validator("key_prefix", "pack_id")
    @classmethod
    def _key_chunk(cls, v: str) -> str:
        if (problem := key_chunk_problem(v)) is not None:
            raise ValueError(problem)
        return v


class MetricsConfig(_Section):
    """An optional Prometheus ``/metrics`` endpoint (needs the ``prometheus-client`` package)."""

    enabled: bool = False
    host: str = Field("127.0.0.1", min_length=1, description="address to bind; loopback by default")
    port: int = Field(9464, ge=0, le=65535, description="TCP port (0 = any free port)")


def default_checkpoint_path() -> Path:
    """``$STATE_DIRECTORY/socd-state.npz``, else ``socd-state.npz`` in the working directory.

    systemd sets ``STATE_DIRECTORY`` for a unit with ``StateDirectory=`` (a colon-separated
    list; the first is ours), and the Docker image sets it to its state volume, so a config
    without ``[checkpoint] path`` checkpoints to the one directory the service may write.
    """
    state_dir = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(state_dir or ".") / CHECKPOINT_FILE_NAME


#: the first bytes of every checkpoint file (:mod:`service.daemon.checkpoint` writes them)
CHECKPOINT_MAGIC = b"SOCD-CHECKPOINT\n"


class CheckpointConfig(_Section):
    path: Path = Field(default_factory=default_checkpoint_path)

    @field_validator("path")
    @classmethod
    def _a_file(cls, v: Path) -> Path:
        """A folder here would be moved aside as an unusable checkpoint at start-up, and any other
        file that is not a checkpoint (a recording, this config) would be moved aside, then
        overwritten by the next save."""
        if str(v) in ("", ".") or v.is_dir():
            raise ValueError(f"{str(v) or '(empty)'} is a folder; give the checkpoint's file path")
        if (problem := special_file_problem(v)) is not None:
            raise ValueError(f"{problem}; give the checkpoint's file path (the service replaces it at every save)")
        try:
            with v.open("rb") as f:
                head = f.read(len(CHECKPOINT_MAGIC))
        except OSError:
            return v  # absent (the first start) or unreadable: the daemon reports it at restore
        if head and not CHECKPOINT_MAGIC.startswith(head):
            raise ValueError(f"{v} is an existing file that is not a socd checkpoint; the service would move it "
                             "aside and write its state there: give another path")
        return v
    interval_s: float = Field(30.0, gt=0)
    max_age_s: float = Field(
        10.0, gt=0, description="a restored state older than this (checkpoint time to first new "
        "sample) has its SOC sigma widened by aged_c_rate x age")
    aged_c_rate: float = Field(
        1.0, gt=0, description="mean C-rate the pack is assumed able to have run at while the daemon was down")


class PackConfig(_Section):
    n_cells: int = Field(96, ge=1, le=1024)


# ---------------------------------------------------------------------------------------
# the whole config
# ---------------------------------------------------------------------------------------
class SocdConfig(BaseSettings):
    """Everything the daemon and the replay tool need; see the module docstring."""

    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX,
        env_nested_delimiter=ENV_NESTED_DELIMITER,
        extra="forbid",
        case_sensitive=False,
    )

    bus: BusConfig = BusConfig()
    dbc: DbcConfig = DbcConfig()
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    cell_profile: Path = DEFAULT_CELL_PROFILE
    estimator: EstimatorSettings = EstimatorSettings()
    output: OutputConfig = OutputConfig()
    zenoh: ZenohConfig = ZenohConfig()
    checkpoint: CheckpointConfig = CheckpointConfig()
    pack: PackConfig = PackConfig()
    metrics: MetricsConfig = MetricsConfig()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # the file arrives as init kwargs; the environment overrides it
        return (env_settings, init_settings)

    _profile_file = field_validator("cell_profile")(_regular_file)

    @model_validator(mode="after")
    def _consistent(self) -> SocdConfig:
        m = self.mapping
        explicit_n = "n_cells" in self.pack.model_fields_set
        if not explicit_n and (m.cell_voltage_signals or m.cells):
            # infer the pack size from an explicit mapping
            n = len(m.cell_voltage_signals) or (max(c.cell for c in m.cells) + 1)
            self.pack = PackConfig(n_cells=n)
        n = self.pack.n_cells
        m.expand(n)
        if len(m.cell_voltage_signals) != n:
            raise ValueError(
                f"mapping.cell_voltage_signals: has {len(m.cell_voltage_signals)} signals but "
                f"pack.n_cells is {n}"
            )
        seen: dict[str, str] = {}
        counters: list[tuple[str, str]] = []
        for path, name in m.all_signals():
            if path.startswith("mapping.counter_signals"):
                counters.append((path, name))
                continue
            if name in seen:
                raise ValueError(f"{path}: signal {name!r} is already mapped as {seen[name]}")
            seen[name] = path
        for path, name in counters:  # replay would write its count into the measurement, run read it as one
            if name in seen:
                raise ValueError(f"{path}: signal {name!r} is a measurement ({seen[name]}), not a rolling counter")
        for k, t in enumerate(m.temperature_signals):
            if len(set(t.cells)) < len(t.cells):
                twice = next(c for c in t.cells if t.cells.count(c) > 1)
                raise ValueError(f"mapping.temperature_signals[{k}].cells: cell {twice} is listed twice")
            for j, c in enumerate(t.cells):
                if not 0 <= c < n:
                    raise ValueError(
                        f"mapping.temperature_signals[{k}].cells[{j}]: cell {c} outside 0..{n - 1}"
                    )
        uncovered = [i for i, s in enumerate(m.sensor_of_cell(n)) if s < 0]
        if uncovered:
            raise ValueError(
                f"mapping.temperature_signals: cell(s) {uncovered[:10]} covered by no temperature sensor"
            )
        if n > 256 and self.output.can_enabled:
            raise ValueError("pack.n_cells: the output DBC's 8-bit cell index carries at most 256 cells")
        return self

    # -- helpers -------------------------------------------------------------------------
    def input_db(self):
        """The input DBC as a cantools database (cached per path and mtime)."""
        return load_dbc(self.dbc.input)

    def output_db(self):
        return load_dbc(self.dbc.output)

    def zenoh_key(self, *parts: str | int) -> str:
        """``<key_prefix>/<pack_id>/<parts...>``, e.g. ``zenoh_key("cell", 3, "soc")``."""
        return "/".join([self.zenoh.key_prefix, self.zenoh.pack_id, *map(str, parts)])


# ---------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------
def load_dbc(path: str | Path):
    """Load a DBC with cantools (strict), cached by path and modification time."""
    p = Path(path).resolve()
    return _load_dbc_cached(str(p), p.stat().st_mtime_ns)


@functools.lru_cache(maxsize=16)
def _load_dbc_cached(path: str, _mtime_ns: int):
    import cantools

    return cantools.database.load_file(path, database_format="dbc", strict=True)


_PATH_FIELDS = (("dbc", "input"), ("dbc", "output"), ("cell_profile",), ("checkpoint", "path"),
                ("zenoh", "config_file"))

#: input files socd ships a default of: field -> the packaged file of a given name
_PACKAGED = {("dbc", "input"): dbc_path, ("dbc", "output"): dbc_path, ("cell_profile",): profile_path}
#: the folders of socd's own layout (the repository's and the package's): a relative path that is a bare
#: name or goes through one of them (the examples' ``../dbc/bms_pack.dbc``, ``configs/vcan0.toml``) and is
#: not there is socd's packaged file of that name; any other missing path stays missing and is reported,
#: so a config or DBC of one's own that was not deployed is never replaced by the example
PACKAGED_LAYOUT_FOLDERS = ("", "configs", "dbc", "cells")


def packaged_layout(p: Path) -> bool:
    """Whether the missing relative path ``p`` may stand for socd's packaged file of its name."""
    return p.parent.name in PACKAGED_LAYOUT_FOLDERS


def resolve_path(keys: tuple[str, ...], value: str | Path, base: Path) -> Path:
    """A config path made absolute: against ``base``; for an input file that is not there,
    the packaged file of that name if socd ships one and the path is of socd's layout
    (:func:`packaged_layout`; else ``base / value``, which :func:`check_config_files` reports as
    missing)."""
    p = Path(value).expanduser()
    if p.is_absolute():
        return p
    local = (base / p).resolve()
    packaged = _PACKAGED.get(keys)
    if packaged is not None and not local.exists() and packaged_layout(p) and packaged(p.name).is_file():
        return packaged(p.name)
    return local


def _resolve_relative(raw: dict[str, Any], base: Path) -> None:
    for keys in _PATH_FIELDS:
        node: Any = raw
        for k in keys[:-1]:
            node = node.get(k) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(keys[-1]), str):
            node[keys[-1]] = str(resolve_path(keys, node[keys[-1]], base))


def format_loc(loc: tuple[Any, ...]) -> str:
    """``('mapping', 'cell_voltage_signals', 3)`` -> ``mapping.cell_voltage_signals[3]``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _section_model(annotation: Any) -> type[BaseModel] | None:
    """The model a field holds (``BusConfig``, the ``CellVoltageMap`` of ``list[CellVoltageMap]``), or None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    return next((m for a in typing.get_args(annotation) if (m := _section_model(a)) is not None), None)


def unknown_key_message(model: type[BaseModel], loc: tuple[Any, ...]) -> str:
    """What to say of a key at ``loc`` that ``model`` has no field for: "unknown key", and the key
    it may have been meant as (``bus.chanel`` -> channel), found among the keys of its section."""
    section: type[BaseModel] | None = model
    for part in loc[:-1]:
        if section is None:
            break
        if not isinstance(part, int):
            field = section.model_fields.get(str(part))
            section = _section_model(field.annotation) if field is not None else None
    keys = list(section.model_fields) if section is not None else []
    near = difflib.get_close_matches(str(loc[-1]), keys, n=1, cutoff=0.6)
    return f"unknown key (did you mean {near[0]}?)" if near else "unknown key (socd schema lists the keys)"


def format_validation_error(exc: ValidationError, source: str, model: type[BaseModel] | None = None) -> str:
    """One line per problem, ``<source>: <section.key>: <problem>``; with the ``model`` validated, a key
    it does not have is called unknown (pydantic's "Extra inputs are not permitted"), with the key meant."""
    lines = []
    for err in exc.errors():
        msg = validation_message(err)
        if model is not None and err["type"] == "extra_forbidden" and err["loc"]:
            msg = unknown_key_message(model, tuple(err["loc"]))
        loc = format_loc(tuple(err["loc"]))
        # cross-field checks name their own field at the start of the message
        lines.append(f"{source}: {loc}: {msg}" if loc else f"{source}: {msg}")
    return "\n".join(lines)


def build_config(raw: dict[str, Any], source: str = "<config>", base_dir: Path | None = None) -> SocdConfig:
    """Validate a config dict (as read from TOML); raise :class:`ConfigError`."""
    raw = _deepcopy(raw)
    if base_dir is not None:
        _resolve_relative(raw, base_dir)
    overrides = sorted(k for k in os.environ if k.upper().startswith(ENV_PREFIX))
    for name in overrides:
        if (hint := unknown_override(name)) is not None:
            log.warning("%s", hint)
    try:
        return SocdConfig(**raw)
    except ValidationError as exc:
        text = format_validation_error(exc, source, SocdConfig)
        if overrides:  # the bad value may be the environment's, not the file's
            text += f" (the environment overrides the file: {', '.join(overrides)})"
        raise ConfigError(text) from None
    except ValueError as exc:  # pydantic-settings' SettingsError: an override it cannot parse
        text = f"{source}: {exc}"
        if overrides:
            text += (f" (the environment overrides the file: {', '.join(overrides)}; a list or table there is "
                     """JSON, e.g. SOCD_ZENOH__LISTEN='["tcp/127.0.0.1:7447"]')""")
        raise ConfigError(text) from None


def override_names(model: type[BaseModel], prefix: str) -> Iterator[str]:
    """Every environment variable name that sets a field of ``model`` or a whole section (upper case)."""
    for field, info in model.model_fields.items():
        name = f"{prefix}{field.upper()}"
        yield name
        kind = info.annotation
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            yield from override_names(kind, name + "__")


@functools.cache
def known_overrides() -> tuple[str, ...]:
    """Every ``SOCD_*`` name that sets a config field or section, sorted (read once)."""
    return tuple(sorted(override_names(SocdConfig, ENV_PREFIX)))


def override_of(*keys: str) -> str | None:
    """The environment variable that sets the field at ``keys`` (``"checkpoint", "path"``) as it is
    spelt in the environment, or None where none does."""
    wanted = ENV_PREFIX + ENV_NESTED_DELIMITER.join(keys).upper()
    return next((k for k in os.environ if k.upper() == wanted), None)


def unknown_override(name: str) -> str | None:
    """A warning for a ``SOCD_*`` variable that sets no config field.  One outside every section is
    ignored (a typo would otherwise pass unseen); one inside a section (``SOCD_BUS__CHANEL``) is an
    unknown field of it, which the config then refuses, as it refuses one in the file."""
    known = known_overrides()
    if name.upper() in known:
        return None
    near = difflib.get_close_matches(name.upper(), known, n=1, cutoff=0.8)  # SOCD_FOO is no SOCD_ZENOH
    section = name.upper()[len(ENV_PREFIX):].split(ENV_NESTED_DELIMITER, 1)[0]
    inside = ENV_NESTED_DELIMITER in name and f"{ENV_PREFIX}{section}" in known
    return (f"environment variable {name} sets no config field"
            + (f" of [{section.lower()}], which refuses it" if inside else "; it is ignored")
            + (f" (did you mean {near[0]}?)" if near else ""))


def _deepcopy(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _deepcopy(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_deepcopy(v) for v in d]
    return d


def find_config(path: str | Path | None) -> Path:
    """The config file ``path`` names: the file itself if it exists (or is absolute), else the
    packaged example of that relative path or file name (``socketcan_can0.toml``,
    ``configs/vcan0.toml``; :func:`packaged_layout`); ``None`` is the packaged ``default.toml``."""
    if path is None:
        return DEFAULT_CONFIG
    p = Path(path).expanduser()
    if p.is_absolute() or p.exists():
        return p
    for candidate in (config_path(str(p)), config_path(p.name) if packaged_layout(p) else None):
        if candidate is not None and candidate.is_file():
            log.info("config %s: not in the working directory; using socd's example %s", p, candidate)
            return candidate
    return p


def load_config(path: str | Path | None = None, *, check_files: bool = True) -> SocdConfig:
    """Load ``path`` (see :func:`find_config`; default the packaged ``default.toml``), apply
    ``SOCD_*`` env, validate.

    With ``check_files`` (default) also checks that both DBCs load, that every mapped signal
    exists in ``dbc.input`` (naming the first missing one), that ``dbc.output`` has the
    frames the encoder writes, and that ``cell_profile`` exists.
    """
    path = find_config(path)
    if (problem := special_file_problem(path)) is not None:
        raise ConfigError(f"{path}: cannot read config: {problem}")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a BOM from a Windows editor is not TOML
    except OSError as exc:
        raise ConfigError(
            f"{path}: cannot read config: {exc.strerror or exc} "
            f"(socd ships these examples: {', '.join(example_configs())})"
        ) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text (UTF-8) TOML file: byte {exc.start}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    config = build_config(raw, str(path), path.resolve().parent)
    # relative paths from the environment resolve against the working directory
    for keys in _PATH_FIELDS:
        obj: Any = config
        for k in keys[:-1]:
            obj = getattr(obj, k)
        p = getattr(obj, keys[-1])
        if p is not None and not p.is_absolute():
            setattr(obj, keys[-1], resolve_path(keys, p, Path.cwd()))
    if check_files:
        check_config_files(config, str(path))
    return config


def dbc_load_problem(exc: BaseException) -> str:
    """cantools' error on a DBC it cannot parse, in one readable line: the parser's first line, cut to
    a length a terminal shows (a binary file puts its bytes in it), and what an index error from the
    parser means (cantools passes it on in its own error's text): a file that ends mid-definition."""
    detail = " ".join(str(exc).split()) or type(exc).__name__
    detail = detail if len(detail) <= 120 and detail.isprintable() else repr(detail[:80]) + "..."
    if isinstance(exc, (IndexError, KeyError)) or "index out of range" in detail:
        return f"the file ends inside a definition, or is no DBC (cantools: {detail})"
    return detail


def _load_config_dbc(config: SocdConfig, field: str, source: str):
    p = getattr(config.dbc, field)
    try:
        db = load_dbc(p)
    except FileNotFoundError:
        raise ConfigError(f"{source}: dbc.{field}: no such file {p}{_no_packaged(p, dbc_path)}") from None
    except Exception as exc:  # cantools raises many kinds for a bad file
        raise ConfigError(f"{source}: dbc.{field}: cannot load DBC {p}: {dbc_load_problem(exc)}") from None
    if (twice := shared_frame_id(db)) is not None:
        raise ConfigError(f"{source}: dbc.{field}: {twice}")
    return db


def shared_frame_id(db: Any) -> str | None:
    """Two messages of a DBC with one frame ID, or None: cantools keeps the later one for the ID, so
    every frame would decode as that message."""
    seen: dict[tuple[int, bool], str] = {}
    for msg in db.messages:
        key = (msg.frame_id, bool(msg.is_extended_frame))
        if key in seen:
            return (f"messages {seen[key]} and {msg.name} share frame ID 0x{msg.frame_id:X}: every frame of that ID "
                    f"would decode as {msg.name}")
        seen[key] = msg.name
    return None


#: what socd sends in the output DBC's signals, beyond the cell indices: SOC in %
OUTPUT_SOC_SIGNALS = ("SOCD_Soc", "SOCD_SocMin", "SOCD_SocMean", "SOCD_SocMax")
OUTPUT_CELL_INDEX_SIGNALS = ("SOCD_SocCellIndex", "SOCD_ParCellIndex", "SOCD_SocMinCell", "SOCD_SocMaxCell")


def signal_reach(sig: Any) -> tuple[float, float]:
    """The physical values a DBC signal can carry: its raw range through scale and offset, within
    its minimum and maximum."""
    n = int(sig.length)
    raw = (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if sig.is_signed else (0, 2 ** n - 1)
    lo, hi = sorted(r * sig.scale + sig.offset for r in raw)
    if sig.minimum is not None:
        lo = max(lo, float(sig.minimum))
    if sig.maximum is not None:
        hi = min(hi, float(sig.maximum))
    return lo, hi


def output_range_problems(db_out: Any, n_cells: int) -> Iterator[str]:
    """Output signals that cannot carry what socd sends: SOC over 0-100 %, a cell index up to
    ``n_cells - 1``; encoded anyway, such a signal would publish a clipped or wrapped value."""
    needs = {**{name: (0.0, 100.0) for name in OUTPUT_SOC_SIGNALS},
             **{name: (0.0, float(n_cells - 1)) for name in OUTPUT_CELL_INDEX_SIGNALS}}
    for msg_name in OUTPUT_MESSAGES:
        for sig in db_out.get_message_by_name(msg_name).signals:
            if sig.name not in needs:
                continue
            if not sig.scale:
                yield f"{msg_name}.{sig.name} has a scale factor of 0"
                continue
            lo, hi = signal_reach(sig)
            want_lo, want_hi = needs[sig.name]
            step = abs(sig.scale) / 2
            if lo > want_lo + step or hi < want_hi - step:
                yield (f"{msg_name}.{sig.name} carries {lo:g} to {hi:g}, but socd sends {want_lo:g} to {want_hi:g}"
                       + (f" (cell indices of {n_cells} cells)" if sig.name in OUTPUT_CELL_INDEX_SIGNALS else " (SOC in %)"))


def check_config_files(config: SocdConfig, source: str = "<config>") -> None:
    """Check the files the config points at and the signal names against the DBCs."""
    check_input_mapping(config, source)
    db_out = _load_config_dbc(config, "output", source)
    if config.output.can_enabled:
        for msg_name, sig_names in OUTPUT_MESSAGES.items():
            try:
                msg = db_out.get_message_by_name(msg_name)
            except KeyError:
                raise ConfigError(f"{source}: dbc.output: message {msg_name!r} missing") from None
            have = {s.name for s in msg.signals}
            for s in sig_names:
                if s not in have:
                    raise ConfigError(f"{source}: dbc.output: signal {s!r} missing from {msg_name}")
        for problem in output_range_problems(db_out, config.pack.n_cells):
            raise ConfigError(f"{source}: dbc.output: {problem}")
    if not config.cell_profile.is_file():
        raise ConfigError(
            f"{source}: cell_profile: no such file {config.cell_profile}"
            f"{_no_packaged(config.cell_profile, profile_path)}"
        )


def check_input_mapping(config: SocdConfig, source: str = "<config>") -> None:
    """The input DBC loads and holds every signal the mapping names (what a replay needs);
    :class:`ConfigError` on the first problem of :func:`mapping_problems`."""
    db_in = _load_config_dbc(config, "input", source)
    for where, why in mapping_problems(config, db_in):
        raise ConfigError(f"{source}: {where}: {why}")


def mapping_problems(config: SocdConfig, db_in: Any) -> Iterator[tuple[str, str]]:
    """``(field, problem)`` for every mapped signal ``db_in`` (the input DBC) does not carry as
    the mapping needs it: missing (with a close name), a counter outside its message, a
    multiplexer switch mapped as a measurement, a multiplexed signal on switch values the
    switch cannot take, a multiplexed time signal."""
    by_name = {s.name: (m, s) for m in db_in.messages for s in m.signals}
    for where, name in config.mapping.all_signals():
        if where.startswith("mapping.counter_signals."):
            msg_name = where.split(".", 2)[2]
            try:
                msg = db_in.get_message_by_name(msg_name)
            except KeyError:
                yield where, f"message {msg_name!r} not in dbc.input ({config.dbc.input.name})"
                continue
            if name not in {s.name for s in msg.signals}:
                yield where, f"signal {name!r} not in message {msg_name!r} of dbc.input"
            continue
        if name not in by_name:
            hint = _close(name, by_name)
            yield where, (f"signal {name!r} not in dbc.input ({config.dbc.input.name})"
                          + (f"; did you mean {hint!r}?" if hint else ""))
            continue
        msg, sig = by_name[name]
        if sig.is_multiplexer:
            yield where, f"signal {name!r} is the multiplexer switch of {msg.name}, not a measurement"
            continue
        if not sig.scale:
            yield where, f"signal {name!r} of {msg.name} has a scale factor of 0: every raw value decodes to its offset"
            continue
        if where == "mapping.time_signal" and sig.multiplexer_ids:
            yield where, f"signal {name!r} is multiplexed in {msg.name}; a time must be in every frame of its message"
            continue
        if sig.multiplexer_ids:
            switch = msg.get_signal_by_name(sig.multiplexer_signal)
            hi = min(2 ** switch.length - 1, int(switch.maximum) if switch.maximum is not None else 2 ** 63)
            lo = max(0, int(switch.minimum) if switch.minimum is not None else 0)
            bad = [v for v in sig.multiplexer_ids if not lo <= v <= hi]
            if bad:
                yield where, (f"signal {name!r} is multiplexed on {switch.name} value(s) {bad}, outside "
                              f"the switch's range {lo}..{hi}")


def _no_packaged(missing: Path, packaged: Callable[[str], Path]) -> str:
    """The tail of a missing-file error: what socd ships of that kind, and where."""
    own = packaged(missing.name)
    if own.is_file():
        return f" (socd's own {missing.name} is {own})"
    names = sorted(p.name for p in own.parent.iterdir() if p.suffix == missing.suffix)
    return f", and socd ships no file of that name (it ships {', '.join(names)} in {own.parent})"


def _close(name: str, names) -> str | None:
    import difflib

    m = difflib.get_close_matches(name, list(names), n=1)
    return m[0] if m else None
