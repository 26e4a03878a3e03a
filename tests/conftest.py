"""Shared test settings: a small, deterministic hypothesis profile so the suite stays fast in CI."""

from hypothesis import HealthCheck, settings

settings.register_profile(
    "socnav", max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("socnav")
