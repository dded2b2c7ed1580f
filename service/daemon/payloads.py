"""JSON payloads on the Zenoh key expressions (DESIGN §5), one pydantic model per key.

Every payload carries ``schema_version``; a consumer should reject a major version it does
not know.  A payload's version moves when its own shape changes (:data:`SCHEMA_VERSION` for
those unchanged since the first release; ``Summary`` and the ``Snapshot`` that holds one are
at :data:`SUMMARY_SCHEMA_VERSION` since they gained the pack view).  SOC is in percent on
the wire (DESIGN §3), everything else in SI units named in the field.  ``t_s`` is the frame
timestamp of the newest sample the estimate includes.

Key expressions (``<prefix>/<pack>/...``, see :func:`keys`):

=========================  ===================  ===============================================
key                        model                when
=========================  ===================  ===============================================
``cell/<i>/soc``           :class:`CellSoc`     when estimated; every ``output.zenoh_period_s`` if not
``cell/<i>/params``        :class:`CellParams`  every ``output.zenoh_period_s``
``summary``                :class:`Summary`     when estimated; every ``output.zenoh_period_s`` if not
``health``                 :class:`Health`      every ``output.zenoh_period_s``
``snapshot`` (queryable)   :class:`Snapshot`    on request: latest state of every cell
=========================  ===================  ===============================================

No key is put more often than once per ``output.min_publish_interval_s`` (the newest value
of a key held back goes out when its interval has passed).
"""

from __future__ import annotations

from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

SCHEMA_VERSION = 1
#: version of :class:`Summary` and :class:`Snapshot`: 2 added the pack view (usable SOC, energy, imbalance)
SUMMARY_SCHEMA_VERSION = 2
#: :class:`CellParams` gained the capacity and resistance-growth fields (all optional: a
#: version-1 consumer that ignores unknown fields still reads the rest)
PARAMS_SCHEMA_VERSION = 2


class _Payload(BaseModel):
    model_config = ConfigDict(extra="forbid")

    schema_version: int = SCHEMA_VERSION
    pack: str
    t_s: float = Field(description="frame timestamp of the newest sample in this estimate, s")


class CellSoc(_Payload):
    cell: int = Field(ge=0)
    soc_pct: float | None = Field(description="state of charge, %; null before the first estimate")
    soc_std_pct: float | None = Field(
        description="1-σ uncertainty of soc_pct, %: the filter's own and what an OCV-table error and a current-sensor "
        "offset it does not model add (estimator.reported_ocv_error_v, reported_current_offset_c)")
    voltage_v: float | None = Field(description="last measured terminal voltage, V")
    v_pred_v: float | None = Field(None, description="model-predicted terminal voltage, V")
    stale: bool = Field(description="inputs older than mapping.stale_after_s: estimate not updated")
    resets: int = Field(0, description="filter re-initialisations of this cell since start")


class CellParams(_Payload):
    """Identified MTS-FOM parameters (Zeng Fig. 1); C's are CPE coefficients, F·s^(α-1).
    Schema 2 adds the cell's state of health (:meth:`PackEstimator.health`)."""

    schema_version: int = PARAMS_SCHEMA_VERSION
    cell: int = Field(ge=0)
    r_ohm: float | None = None
    r_ct: float | None = None
    c_dl: float | None = None
    m: float | None = None
    r_df: float | None = None
    c_df: float | None = None
    n: float | None = None
    capacity_ah: float | None = Field(None, description="estimated capacity, Ah (the profile's when frozen)")
    capacity_std_ah: float | None = Field(None, description="1-σ uncertainty of capacity_ah, Ah (0 when frozen)")
    capacity_pct: float | None = Field(None, description="capacity / the profile's capacity, % (SOH-energy)")
    resistance_pct: float | None = Field(
        None, description="(R_ohm + R_ct) / the profile's at the cell's temperature and SOC, % (SOH-power)")


class Summary(_Payload):
    """Pack SOC over the cells with an estimate, and the pack view of
    :mod:`service.estimators.pack_view` (usable SOC limited by the weakest cell each way)."""

    schema_version: int = SUMMARY_SCHEMA_VERSION
    n_cells: int
    soc_mean_pct: float | None
    soc_min_pct: float | None
    soc_max_pct: float | None
    cell_min: int | None = Field(description="index of the cell with the lowest SOC")
    cell_max: int | None = Field(description="index of the cell with the highest SOC")
    soc_std_max_pct: float | None
    current_a: float | None = Field(description="pack current, A, positive = discharge")
    n_stale: int
    status_flags: dict[str, bool]
    usable_soc_pct: float | None = Field(
        None, description="D / (D + H), %: D = min_i SOC_i·C_i, H = min_i (1 − SOC_i)·C_i; null when undefined")
    usable_discharge_ah: float | None = Field(None, description="D: charge the weakest cell can still give, Ah")
    usable_charge_ah: float | None = Field(None, description="H: charge the fullest cell can still take, Ah")
    remaining_energy_wh: float | None = Field(
        None, description="Σ_i C_i ∫_0^SOC_i OCV_i(s) ds over the profile's OCV model, Wh (open-circuit)")
    usable_energy_wh: float | None = Field(
        None, description="the part of remaining_energy_wh delivered before the weakest cell is empty, Wh")
    imbalance_ah: float | None = Field(None, description="max_i SOC_i·C_i − min_i SOC_i·C_i, Ah")
    weakest_cell: int | None = Field(None, description="index of the cell holding the least charge (limits discharge)")
    fullest_cell: int | None = Field(None, description="index of the cell with the least room (limits charge)")


class Health(_Payload):
    uptime_s: float
    status_flags: dict[str, bool]
    counters: dict[str, int] = Field(description="event counts by reason since start")
    latency_ms: dict[str, float | None] = Field(
        description="frame timestamp → estimate ('estimate_p50/p99') and → Zenoh put ('publish_p50/p99')"
    )
    checkpoint: str = Field(description="how this run started: 'restored', or the reason it could not")


class Snapshot(_Payload):
    """Answer of the ``snapshot`` queryable: everything a dashboard needs to join late."""

    schema_version: int = SUMMARY_SCHEMA_VERSION
    cells: list[CellSoc]
    params: list[CellParams]
    summary: Summary
    health: Health


@dataclass(frozen=True)
class Keys:
    """Key expressions of one pack under a prefix."""

    prefix: str
    pack: str

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.pack}"

    def cell_soc(self, i: int) -> str:
        return f"{self.base}/cell/{i}/soc"

    def cell_params(self, i: int) -> str:
        return f"{self.base}/cell/{i}/params"

    @property
    def summary(self) -> str:
        return f"{self.base}/summary"

    @property
    def health(self) -> str:
        return f"{self.base}/health"

    @property
    def snapshot(self) -> str:
        return f"{self.base}/snapshot"


def keys(prefix: str, pack: str) -> Keys:
    return Keys(prefix.strip("/"), pack)
