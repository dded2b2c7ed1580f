"""The cell model (Zeng et al., MTS-FOM): OCV, hysteresis, fractional CPE branches, profiles."""
