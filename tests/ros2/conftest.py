"""Fixtures of the ROS 2 tests: the `ros2` marker's skip, an exported navigator, and an isolated ROS 2 graph.

Tests marked ``ros2`` are skipped, with the reason, where rclpy does not import (the ``ros2`` extra is optional and
not part of the ``test`` extra). Nodes of the test process alone run with discovery off; a graph of processes is
loopback only (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) on a random ``ROS_DOMAIN_ID`` (a share of them per
pytest-xdist worker), so that tests running at the same time on one machine do not see each other's nodes.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest

from socnav.ros2.environment import Ros2Unavailable, require_rclpy

#: Domain ids whose Fast DDS ports stay below Linux's ephemeral range (the ROS 2 docs' advice: 0 to 101).
DOMAIN_IDS = range(1, 102)


def _rclpy_problem() -> str | None:
    try:
        require_rclpy()
    except Ros2Unavailable as exc:
        return str(exc)
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    marked = [item for item in items if item.get_closest_marker("ros2")]
    problem = _rclpy_problem() if marked else None
    if problem:
        skip = pytest.mark.skip(reason=f"ROS 2 is not available: {problem}")
        for item in marked:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def navigator_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped policy exported as `socnav export` writes it (paper MC-dropout thresholds, K = 20)."""
    import torch

    import socnav

    torch.set_num_threads(1)
    return socnav.export_onnx(socnav.load_policy("pretrained"), tmp_path_factory.mktemp("ros2") / "navigator.onnx")


def _domain_id() -> int:
    """A random domain id, from a share of :data:`DOMAIN_IDS` of this pytest-xdist worker's own (two workers never
    pick the same one)."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    return random.choice([domain for domain in DOMAIN_IDS if domain % workers == worker % workers])


def _context(domain: int):
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context, domain_id=domain)
    return context


def _shut_down(context) -> None:
    import rclpy

    if context.ok():
        rclpy.shutdown(context=context)


@pytest.fixture
def ros_environment(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """This test's graph of processes: loopback discovery on a random domain; the environment for its ROS 2
    processes (also set in this process)."""
    settings = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(_domain_id())}
    for name, value in settings.items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    return {**os.environ, **settings}


@pytest.fixture
def ros_graph_context(ros_environment: dict[str, str]):
    """An rclpy context in this process that joins the test's graph of processes."""
    context = _context(int(ros_environment["ROS_DOMAIN_ID"]))
    yield context
    _shut_down(context)


@pytest.fixture
def ros_context(monkeypatch: pytest.MonkeyPatch):
    """An rclpy context for nodes of this process only: discovery off (``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``), so
    nothing outside the process can reach them, whatever the domain."""
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    monkeypatch.delenv("ROS_STATIC_PEERS", raising=False)
    context = _context(_domain_id())
    yield context
    _shut_down(context)
