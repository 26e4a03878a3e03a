"""Batched crowd simulator: the world, human models (ORCA, social force; `socnav.sim.humans`), scenarios (with walls:
`socnav.sim.map_scenarios`), walls and sensing noise."""

from socnav.sim import map_scenarios  # noqa: F401  (registers the scenarios with walls beside the paper's four)
