"""The cell model (Zeng et al., MTS-FOM): OCV, hysteresis, fractional CPE branches, profiles,
and the SOC bookkeeping around it: coulomb counting and the truth SOC of a recording."""
