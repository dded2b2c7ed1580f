"""The names of the MTS-FOM parameters (Zeng Fig. 1), in the order every output lists them.

They are the fields of :class:`service.cell.profile.ParameterPoint` (besides its temperature
and the optional exchange current): the ohmic resistance, the charge-transfer branch
(``r_ct``, CPE ``c_dl`` of order ``m``) and the diffusion branch (``r_df``, CPE ``c_df`` of
order ``n``).  The estimators' traces, the CAN parameter frames and the Zenoh payloads use
these keys.
"""

from __future__ import annotations

PARAMETER_NAMES: tuple[str, ...] = ("r_ohm", "r_ct", "c_dl", "m", "r_df", "c_df", "n")
