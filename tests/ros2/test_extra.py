"""The ros2 extra: pinned to one ROS 2 distribution, optional (nothing but the ros2 commands imports rclpy), and
asked for by name when missing. These tests run with or without ROS 2 installed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import tomllib
from typer.testing import CliRunner

from socnav.ros2.environment import MESSAGE_PACKAGES, Ros2Unavailable, require_rclpy

REPO = Path(__file__).resolve().parents[2]


def _ros2_extra() -> list[str]:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]["ros2"]


def test_the_extra_pins_one_jazzy_release_of_everything_the_nodes_import():
    pins = {}
    for requirement in _ros2_extra():
        name, _, version = requirement.partition("==")
        if name.startswith("ros-"):
            assert name.startswith("ros-jazzy-") and version, f"{requirement}: pin ROS packages to a Jazzy release"
            pins[name.removeprefix("ros-jazzy-")] = version
    # rcl_interfaces and builtin_interfaces come with rclpy (ros-rclpy requires them, pinned ~= to its release)
    imported = {name.replace("_", "-") for name in MESSAGE_PACKAGES} - {"rcl-interfaces", "builtin-interfaces"}
    assert imported | {"rclpy", "rmw-fastrtps-cpp"} <= set(pins)
    assert len({pins[name] for name in ("std-msgs", "geometry-msgs", "nav-msgs", "sensor-msgs",
                                        "visualization-msgs", "diagnostic-msgs")}) == 1  # one common_interfaces


def test_nothing_but_the_ros2_commands_imports_rclpy():
    code = ("import sys, socnav, socnav.cli, socnav.runtime, socnav.ros2, socnav.cli.ros2, socnav.ros2.environment\n"
            "from typer.testing import CliRunner\n"
            "for args in (['--help'], ['ros2', '--help'], ['ros2', 'navigator', '--help'],\n"
            "             ['ros2', 'sim', '--help']):\n"
            "    assert CliRunner().invoke(socnav.cli.app, args).exit_code == 0, args\n"
            "loaded = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rcl_interfaces', 'nav_msgs'))\n"
            "print(loaded); sys.exit(1 if loaded else 0)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("command", [["navigator", "--model", "navigator.onnx"],
                                     ["sim", "--scenario", "circle_crossing", "--episodes", "1"]])
def test_without_the_extra_the_commands_say_how_to_install_it(monkeypatch, tmp_path, command):
    from socnav.cli import app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "rclpy", None)  # as if it were not installed
    with pytest.raises(Ros2Unavailable, match="rclpy"):
        require_rclpy()
    result = CliRunner().invoke(app, ["ros2", *command])
    assert result.exit_code == 2, result.output
    output = " ".join(result.output.split())
    assert "socnav ros2 needs ROS 2 Jazzy" in output and "missing: rclpy" in output
    assert '".[ros2]"' in output or '"socnav[ros2]"' in output


@pytest.mark.parametrize("arguments,message", [
    (["--out", "r.txt"], "--out must end in one of"),
    (["--record", "r.bag"], "--record must end in .mcap"),
    (["--model", "n.onnx", "--config", "c.yaml"], "--model and --config both name the world"),
    (["--scenario", "nowhere"], "unknown scenario 'nowhere'"),
])
def test_the_simulator_refuses_bad_options_before_starting_ros(monkeypatch, tmp_path, arguments, message):
    from socnav.cli import app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "rclpy", None)  # the options are checked first
    result = CliRunner().invoke(app, ["ros2", "sim", *arguments])
    assert result.exit_code == 2 and message in " ".join(result.output.split()), result.output
