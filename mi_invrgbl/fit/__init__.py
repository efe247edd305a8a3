"""Inverse rendering: observations, the two-stage optimisation, losses and model selection."""
