"""The shipped DBCs and their generator (:mod:`generate_dbc`); packaged as ``service.assets.dbc``."""
