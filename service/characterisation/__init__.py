"""Offline characterisation of a cell (``socd fit``): OCV, capacity, model parameters."""
