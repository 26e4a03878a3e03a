"""Batched crowd simulator: ORCA humans, scenarios and sensing noise."""
