"""``socd schema [-o DIR]``: the JSON Schemas of the config and of the Zenoh payloads, and an example of each.

The schemas are the pydantic models' own (:class:`service.config.SocdConfig`,
:mod:`service.daemon.payloads`).  The config's example is the bundled default config as
``socd run`` reads it (its paths resolved on this machine); the payloads' examples are built by
the publisher's own code (:func:`service.daemon.zenoh_pub.build_payloads` and
:class:`service.daemon.health.HealthMonitor`) from a two-cell round with illustrative values,
so they have exactly the shape the daemon publishes.  With ``-o DIR`` it writes
``<name>.schema.json`` and ``<name>.example.json`` for each; without, one JSON document on stdout.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.commands.common_args import add_common_arguments, output_dir, plain_text, setup_logging

EXAMPLE_PACK = "pack0"
EXAMPLE_PREFIX = "bms"


def add_subparser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "schema",
        help="write the JSON Schemas of the config and of the Zenoh payloads, and an example of each",
        description=plain_text(__doc__.split("\n\n")[0]),
    )
    p.add_argument("-o", "--output", type=output_dir, metavar="DIR",
                   help="write <name>.schema.json and <name>.example.json here (default: one JSON document on stdout)")
    add_common_arguments(p)
    p.set_defaults(func=run)


@dataclass(frozen=True)
class PayloadDoc:
    """One payload: its file stem, key expression, model and an example instance."""

    name: str
    key: str
    model: type
    example: Any

    def schema(self) -> dict[str, Any]:
        return self.model.model_json_schema()


def config_doc() -> PayloadDoc:
    """The service config (TOML; ``SOCD_*`` variables override it), the bundled default as its example."""
    from service.config import ENV_NESTED_DELIMITER, ENV_PREFIX, SocdConfig, load_config

    key = f"config file (TOML; {ENV_PREFIX}<SECTION>{ENV_NESTED_DELIMITER}<FIELD> overrides)"
    return PayloadDoc("config", key, SocdConfig, load_config(None, check_files=False))


def payload_docs() -> list[PayloadDoc]:
    """The config, then every Zenoh payload with an example built by the publisher's code."""
    import numpy as np

    from service.bus.types import STATUS_FLAGS
    from service.cell.profile import load_profile
    from service.config import DEFAULT_CELL_PROFILE
    from service.daemon.health import HealthMonitor
    from service.daemon.payloads import CellParams, CellSoc, Health, Snapshot, Summary, keys
    from service.daemon.zenoh_pub import PublishRound, build_payloads
    from service.estimators.pack_view import OcvEnergy, pack_view

    now = [0.0]
    health = HealthMonitor(pack=EXAMPLE_PACK, clock=lambda: now[0])
    now[0] = 3600.0  # an hour of uptime
    health.count("frames_in", 24000)
    health.count("can_frames_out", 1200)
    health.count("zenoh_messages", 3000)
    health.record_latency("estimate", 0.0008)
    health.record_latency("publish", 0.0031)
    health.checkpoint_state = "restored"
    # every flag of the status word, as the daemon publishes them; this one restored its checkpoint
    flags = {name: name == "checkpoint_restored" for name in STATUS_FLAGS}
    t_s = 1732443600.25
    soc = np.array([0.8123, 0.8087])
    profile = load_profile(DEFAULT_CELL_PROFILE)  # the pack view of two bundled cells, one faded by 3 %
    capacity = profile.effective_capacity_ah * np.array([1.0, 0.97])
    view = pack_view(soc, capacity, OcvEnergy(profile.ocv_table()), np.array([24.5, 25.0]))
    r = PublishRound(
        t_s=t_s,
        soc=soc,
        soc_std=np.array([0.0042, 0.0045]),
        voltage_v=np.array([3.9812, 3.9776]),
        stale=np.array([False, False]),
        params={"r_ohm": np.array([0.0231, 0.0236]), "r_ct": np.array([0.0112, 0.0118]),
                "c_dl": np.array([512.0, 498.0]), "m": np.array([0.78, 0.79]),
                "r_df": np.array([0.0191, 0.0203]), "c_df": np.array([4850.0, 4710.0]), "n": np.array([0.61, 0.6])},
        health=health.payload(t_s, {}, flags),
        status_flags=flags,
        current_a=5.42,
        v_pred=np.array([3.9809, 3.9781]),
        resets=np.array([0, 0]),
        pack=view,
    )
    p = build_payloads(EXAMPLE_PACK, r)
    snapshot = Snapshot(pack=EXAMPLE_PACK, t_s=t_s, cells=p.cells, params=p.params, summary=p.summary,
                        health=p.health)
    k = keys(EXAMPLE_PREFIX, EXAMPLE_PACK)
    return [config_doc(),
        PayloadDoc("cell_soc", f"{k.base}/cell/<i>/soc", CellSoc, p.cells[0]),
        PayloadDoc("cell_params", f"{k.base}/cell/<i>/params", CellParams, p.params[0]),
        PayloadDoc("summary", k.summary, Summary, p.summary),
        PayloadDoc("health", k.health, Health, p.health),
        PayloadDoc("snapshot", f"{k.snapshot} (queryable)", Snapshot, snapshot),
    ]


def run(args: argparse.Namespace) -> int:
    setup_logging(args)
    docs = payload_docs()
    if args.output is None:
        doc = {d.name: {"key": d.key, "schema": d.schema(), "example": d.example.model_dump(mode="json")}
               for d in docs}
        print(json.dumps(doc, indent=1))
        return 0
    out = Path(args.output)  # an existing file was refused as the argument (output_dir)
    out.mkdir(parents=True, exist_ok=True)
    for d in docs:
        (out / f"{d.name}.schema.json").write_text(json.dumps(d.schema(), indent=1) + "\n")
        (out / f"{d.name}.example.json").write_text(d.example.model_dump_json(indent=1) + "\n")
        print(f"{d.key:32s} {out / (d.name + '.schema.json')}  {out / (d.name + '.example.json')}")
    return 0
