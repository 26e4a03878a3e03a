"""Batched crowd simulator: the world, human models (ORCA, social force; `socnav.sim.humans`), scenarios and sensing
noise."""
