"""Evaluation beyond the per-stage figures: stability sweeps (light orbit, expression magnitude) and limits."""
