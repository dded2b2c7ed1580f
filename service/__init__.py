"""socd: streaming battery state estimator (MTS-FOM + FO-MI-UKF) beside a BMS CAN bus."""

__version__ = "0.1.0"
