"""Metrics, quality-versus-horizon curves and plots."""
