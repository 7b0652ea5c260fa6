"""Diagnostics a user runs on a trained policy (``dust-rl diagnose ...``): measurements, not training."""
