"""Samplers and guidance (pure torch): stateless objects shared by validation and pipelines."""
