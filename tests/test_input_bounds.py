"""Every file socnav reads is bounded before the expensive step, so that an input an attacker shaped costs nothing:
replay trajectory files, map YAML, map images, configs and thresholds files, navigator files. Each crafted input
below is refused with one line naming the file, the limit and the value -- within seconds, and under a memory limit:
the loads run in a subprocess whose address space is capped at what its imports took plus 1 GiB
(`resource.RLIMIT_AS`), so a regression fails with a MemoryError instead of taking the machine's memory. Large files
are sparse (`truncate`): refusing them from their size costs nothing. docs/limits.md lists the limits and the
measured peak memory.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

from socnav.config import YAML_MAX_BYTES, YAML_MAX_DEPTH, YAML_MAX_NODES, ConfigError, load_config
from socnav.sim import maps
from socnav.sim.humans import replay, trajectories
from socnav.sim.maps import MAX_COORDINATE, MapError, validate_polygons

REPO = Path(__file__).resolve().parents[1]
#: A refusal takes well under a second on an idle machine; the margin is for a loaded test machine.
SECONDS = 10.0
#: What a refusal may add to the peak resident memory of the process (the largest is the 1 MiB map of vertices).
PEAK_MB = 300

BILLION_LAUGHS = "".join(
    ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n']
    + [f"{name}: &{name} [{','.join(['*' + previous] * 9)}]\n"
       for previous, name in zip("abcdefgh", "bcdefghi", strict=True)]
)


def _png(width: int, height: int) -> bytes:
    """A valid 1-bit greyscale PNG header declaring `width` x `height`, with a few bytes of pixel data (a
    decompression bomb as far as the header goes: no decoder must ever see it)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([1, 0, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(
        b"IEND", b"")


def _sparse(path: Path, size: int, head: bytes = b"") -> Path:
    with open(path, "wb") as stream:
        stream.write(head)
        stream.truncate(size)
    return path


def _grid_yaml(directory: Path, image: str) -> Path:
    path = directory / f"grid_{image}.yaml"
    path.write_text(f"image: {image}\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\noccupied_thresh: 0.65\n"
                    "free_thresh: 0.196\n")
    return path


def _write_inputs(directory: Path) -> dict[str, tuple[str, str, list[str]]]:
    """The crafted files: case -> (loader, path, words the one-line message must hold)."""
    d = directory
    (d / "evil4.txt").write_text("0 1 0 0\n1000000000 1 1 1\n0 2 0 0\n1 2 1 1\n")
    (d / "nul.txt").write_bytes(b"\0" * (8 << 20))
    (d / "newlines.txt").write_bytes(b"\n" * (8 << 20))
    _sparse(d / "huge.txt", 2 << 30)
    (d / "laughs.yaml").write_text(BILLION_LAUGHS)
    (d / "deep.yaml").write_text("obstacles: " + "[" * 5000 + "]" * 5000 + "\n")
    (d / "vertices.yaml").write_text("obstacles:\n  - [" + ", ".join(["[0, 0]"] * 120_000)[: YAML_MAX_BYTES - 40]
                                     + "]\n")
    _sparse(d / "ten_mb.yaml", 10 << 20, b"obstacles:\n")
    (d / "bomb.png").write_bytes(_png(100_000, 100_000))
    (d / "large.png").write_bytes(_png(3000, 3000))
    _sparse(d / "heavy.png", 100 << 20, _png(10, 10))
    for image in ("bomb.png", "large.png", "heavy.png"):
        _grid_yaml(d, image)
    (d / "deep_config.yaml").write_text("a: " + "[" * 5000 + "]" * 5000 + "\n")
    _sparse(d / "huge_config.yaml", 1 << 30)
    (d / "laughs_thresholds.yaml").write_text(BILLION_LAUGHS)
    limit = f"{replay.MAX_SAMPLES:,}"
    return {
        "replay: frames 0 and 10^9 (12 GB of positions)": ("config_replay", "evil4.txt", [
            "humans.replay.files: trajectory files", "1,600,000,003 positions", limit]),
        "replay: the same, counted directly": ("positions", "evil4.txt", ["1,600,000,003", limit]),
        "replay: the same, as a world is built": ("world", "evil4.txt", ["1,600,000,003 positions", limit]),
        "replay: 8 MB of NUL bytes": ("trajectories", "nul.txt", ["line 1", "8,388,608 bytes long",
                                                                  f"{replay.MAX_LINE_BYTES:,}"]),
        "replay: 8 MB of newlines": ("trajectories", "newlines.txt", ["8,388,608 lines", f"{replay.MAX_LINES:,}"]),
        "replay: a 2 GiB file, read directly": ("trajectories", "huge.txt", ["2,147,483,648",
                                                                             f"{replay.MAX_FILE_BYTES:,}"]),
        "replay: a 2 GiB file in a config": ("config_replay", "huge.txt", ["2,147,483,648",
                                                                           f"{replay.MAX_FILE_BYTES:,}"]),
        "map: billion laughs": ("map", "laughs.yaml", ["alias", f"{YAML_MAX_NODES:,}"]),
        "map: nested 5,000 deep": ("map", "deep.yaml", ["nested too deeply", f"{YAML_MAX_DEPTH}"]),
        "map: 1 MiB of vertices": ("map", "vertices.yaml", [f"more than {YAML_MAX_NODES:,} values"]),
        "map: a 10 MB file": ("map", "ten_mb.yaml", ["10,485,760 bytes", f"{maps.MAX_MAP_BYTES:,}"]),
        "map image: 100,000 x 100,000 (PIL's decompression bomb)": (
            "map", "grid_bomb.png.yaml", ["bomb.png", "10,000,000,000 cells", f"{maps.MAX_GRID_CELLS}"]),
        "map image: 3,000 x 3,000": ("map", "grid_large.png.yaml", ["3000 x 3000 cells", f"{maps.MAX_GRID_CELLS}"]),
        "map image: a 100 MB file": ("map", "grid_heavy.png.yaml", ["heavy.png", "104,857,600 bytes",
                                                                      f"{maps.MAX_IMAGE_BYTES:,}"]),
        "config: nested 5,000 deep": ("config", "deep_config.yaml", ["nested too deeply", f"{YAML_MAX_DEPTH}"]),
        "config: a 1 GiB file": ("config", "huge_config.yaml", ["1,073,741,824 bytes", f"{YAML_MAX_BYTES:,}"]),
        "thresholds: billion laughs": ("thresholds", "laughs_thresholds.yaml", ["alias", f"{YAML_MAX_NODES:,}"]),
    }


#: Run in a subprocess: each case's loader, its error (class and message), the time it took and how much it raised
#: the peak resident memory, under an address-space cap of what the imports took plus 1 GiB.
_RUNNER = textwrap.dedent("""
    import json, resource, sys, time
    from pathlib import Path

    from socnav.config import ReplayConfig, load_config
    from socnav.safety.rule import load_thresholds
    from socnav.sim.humans import replay
    from socnav.sim.maps import load_map
    from socnav.sim.world import CrowdWorld

    directory, cases = Path(sys.argv[1]), json.loads(sys.argv[2])
    with open("/proc/self/status") as status:
        virtual = next(int(line.split()[1]) for line in status if line.startswith("VmSize:")) << 10
    resource.setrlimit(resource.RLIMIT_AS, (virtual + (1 << 30), resource.getrlimit(resource.RLIMIT_AS)[1]))

    def replay_config(path):
        return {"scenario": "replay", "humans": {"model": "replay", "replay": {"files": [str(path)]}}}

    def unchecked(path):  # settings past the config's validation (which refuses the file already)
        return ReplayConfig.model_construct(files=[str(path)], sample_rate=2.5, frame_step=None)

    def world(path):
        config = load_config()
        humans = config.humans.model_copy(update={"model": "replay", "replay": unchecked(path)})
        CrowdWorld(config.model_copy(update={"scenario": "replay", "humans": humans}), 1)  # the scene refuses too

    def positions(path):
        replay.check_positions(unchecked(path), 0.25)

    LOADERS = {"world": world, "positions": positions, "trajectories": replay.read_trajectories,
               "config_replay": lambda path: load_config(replay_config(path)), "map": load_map,
               "config": load_config, "thresholds": load_thresholds}
    for case, (loader, name) in cases.items():
        before, start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, time.perf_counter()
        try:
            LOADERS[loader](directory / name)
            error = None
        except MemoryError:
            error = ("MemoryError", "")
        except Exception as exc:
            error = (type(exc).__name__, str(exc))
        seconds = time.perf_counter() - start
        grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) >> 10
        print(json.dumps({"case": case, "error": error, "seconds": seconds, "peak_mb": grown}), flush=True)
""")


@pytest.fixture(scope="module")
def refusals(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[dict, str, list[str]]]:
    directory = tmp_path_factory.mktemp("crafted")
    inputs = _write_inputs(directory)
    cases = {case: (loader, name) for case, (loader, name, _) in inputs.items()}
    done = subprocess.run([sys.executable, "-c", _RUNNER, str(directory), json.dumps(cases)], capture_output=True,
                          text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stdout + done.stderr[-3000:]
    results = {entry["case"]: entry for entry in map(json.loads, done.stdout.splitlines())}
    return {case: (results[case], str(directory / name), words) for case, (_, name, words) in inputs.items()}


EXPECTED_ERRORS = {"replay": ("TrajectoryFileError", "ConfigError"), "map": ("MapError",),
                   "config": ("ConfigError",), "thresholds": ("ThresholdsError",)}


@pytest.mark.parametrize("case", [
    "replay: frames 0 and 10^9 (12 GB of positions)", "replay: the same, counted directly",
    "replay: the same, as a world is built",
    "replay: 8 MB of NUL bytes", "replay: 8 MB of newlines", "replay: a 2 GiB file, read directly",
    "replay: a 2 GiB file in a config", "map: billion laughs", "map: nested 5,000 deep", "map: 1 MiB of vertices",
    "map: a 10 MB file", "map image: 100,000 x 100,000 (PIL's decompression bomb)", "map image: 3,000 x 3,000",
    "map image: a 100 MB file", "config: nested 5,000 deep", "config: a 1 GiB file", "thresholds: billion laughs",
])
def test_a_crafted_input_is_refused_in_one_line_quickly_and_within_memory(refusals, case):
    result, path, words = refusals[case]
    assert result["error"] is not None, f"{case}: accepted"
    kind, message = result["error"]
    assert kind in EXPECTED_ERRORS[case.split(":")[0].split()[0]], (case, kind, message)
    lines = message.splitlines()
    if lines[0].startswith("invalid socnav config"):  # a config's validation error: its headline, then the problem
        lines = lines[1:]
    assert len(lines) == 1 and "Traceback" not in message, message
    for word in [Path(path).name, *words]:
        assert word in message, (case, word, message)
    assert result["seconds"] < SECONDS, (case, result)
    assert result["peak_mb"] < PEAK_MB, (case, result)


def test_the_sample_bound_is_counted_before_anything_is_interpolated(tmp_path, monkeypatch):
    path = tmp_path / "evil4.txt"
    path.write_text("0 1 0 0\n1000000000 1 1 1\n0 2 0 0\n1 2 1 1\n")
    recording = replay.read_trajectories(path)
    assert replay.count_positions([recording], 0.25, 2.5) == 1_600_000_003
    for module in (replay, trajectories):  # each reads the name it imported
        monkeypatch.setattr(module, "interpolate_track", lambda *args: pytest.fail("interpolated before the bound"))
    for build in (lambda: replay.interpolate_tracks(recording, 0.25, 2.5),
                  lambda: replay.build_scenes([recording], 0.25, 2.5)):
        with pytest.raises(replay.TrajectoryFileError, match=r"give 1,600,000,003 positions at time_step 0.25 s; "
                                                             r"socnav keeps at most 50,000,000"):
            build()
    # a sample rate so small that the last frame's step is not a number any more: refused, not an OverflowError
    with pytest.raises(replay.TrajectoryFileError, match=r"socnav counts at most 9,007,199,254,740,992 steps"):
        replay.count_positions([recording], 0.01, 1e-300)


def test_replay_files_are_refused_from_their_size_before_reading(tmp_path, monkeypatch):
    huge = _sparse(tmp_path / "huge.txt", replay.MAX_FILE_BYTES + 1)

    def no_reading(*args, **kwargs):
        raise AssertionError("read before its size was checked")

    monkeypatch.setattr("socnav.io.read_bounded", no_reading)
    with pytest.raises(replay.TrajectoryFileError, match=rf"{huge} is larger than {replay.MAX_FILE_BYTES:,} bytes, "
                                                         rf"the most socnav reads from such a file \(it has "
                                                         rf"{replay.MAX_FILE_BYTES + 1:,}\)"):
        replay.read_trajectories(huge)
    # all the files of a config together
    monkeypatch.setattr(trajectories, "MAX_TOTAL_BYTES", 100)
    small = [tmp_path / f"{name}.txt" for name in "abc"]
    for path in small:
        path.write_text("0 1 0 0\n10 1 1 1\n" * 3)
    with pytest.raises(replay.TrajectoryFileError, match=r"hold 153 bytes together, more than the 100 socnav reads"):
        replay.read_scenes(tuple(str(path) for path in small), 2.5, None, 0.25)
    replay.check_total_size([small[0], small[0], small[0]])  # a file listed again is counted once


def test_a_config_of_a_short_replay_file_of_too_many_positions_is_refused_as_it_is_read(tmp_path):
    """Four lines, frames 0 and 10^9: 1.6 billion positions at time_step 0.25 s (12 GB) -- refused by the config's
    validation, in one line naming the field, counted without interpolating anything."""
    path = tmp_path / "evil4.txt"
    path.write_text("0 1 0 0\n1000000000 1 1 1\n0 2 0 0\n1 2 1 1\n")
    config = {"scenario": "replay", "humans": {"model": "replay", "replay": {"files": [str(path)]}}}
    start = time.perf_counter()
    with pytest.raises(ConfigError) as error:
        load_config(config)
    seconds = time.perf_counter() - start
    headline, *problems = str(error.value).splitlines()
    assert headline == "invalid socnav config (dict):" and len(problems) == 1, str(error.value)
    assert (f"humans.replay.files: trajectory files {path} give 1,600,000,003 positions at time_step 0.25 s; socnav "
            f"keeps at most {replay.MAX_SAMPLES:,}") in problems[0], problems[0]
    assert seconds < SECONDS, seconds  # ~10 ms: the positions are counted, not built
    # a longer time_step gives fewer positions, but not few enough; within the bound the file is accepted
    with pytest.raises(ConfigError, match="give 400,000,002 positions at time_step 1 s"):
        load_config(config, time_step=1.0)
    path.write_text("0 1 0 0\n100 1 1 1\n0 2 0 0\n10 2 1 1\n")
    assert load_config(config).humans.replay.files == [str(path.resolve())]


def test_the_replay_files_of_a_config_are_bounded_together(tmp_path, monkeypatch):
    monkeypatch.setattr(trajectories, "MAX_TOTAL_BYTES", 100)
    files = [tmp_path / f"{name}.txt" for name in "abc"]
    for path in files:
        path.write_text("".join(f"{10 * frame} 1 {frame} 0\n" for frame in range(6)))  # 53 bytes each
    config = {"scenario": "replay", "humans": {"model": "replay", "replay": {"files": [str(p) for p in files]}}}
    load_config(config, humans={"replay": {"files": [str(files[0])] * 3}})  # a file listed again is counted once
    with pytest.raises(ConfigError) as error:
        load_config(config)
    _, *problems = str(error.value).splitlines()
    assert len(problems) == 1 and problems[0].startswith("  - humans.replay.files: trajectory files "), problems
    assert "hold 159 bytes together, more than the 100 socnav reads" in problems[0], problems[0]


def test_read_bounded_refuses_a_file_from_its_size_before_reading(tmp_path, monkeypatch):
    """A regular file larger than the bound is refused from its size (a sparse 2 GiB file: nothing is read); a file
    that reports no size (/proc) is still bounded while reading."""
    import os

    from socnav.io import UntrustedInputError, read_bounded

    huge = _sparse(tmp_path / "navigator.onnx", 2 << 30)
    opened = []
    real_fdopen = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda *args, **kwargs: opened.append(args) or real_fdopen(*args, **kwargs))
    start = time.perf_counter()
    with pytest.raises(UntrustedInputError) as error:
        read_bounded(huge, 512 << 20)
    assert time.perf_counter() - start < SECONDS
    assert str(error.value) == (f"{huge} is larger than {512 << 20:,} bytes, the most socnav reads from such a file "
                                f"(it has {2 << 30:,})")
    # a 2 GiB navigator file: refused from its size, nothing read (it was read up to the 512 MiB bound)
    from socnav.runtime.format import NAVIGATOR_MAX_BYTES
    from socnav.runtime.network import ExportedPolicy, NavigatorLoadError

    with pytest.raises(NavigatorLoadError, match=rf"navigator.onnx is larger than {NAVIGATOR_MAX_BYTES:,} bytes, the "
                                                 rf"most socnav reads from such a file \(it has {2 << 30:,}\)"):
        ExportedPolicy.load(huge)
    assert not opened, "read before its size was checked"
    monkeypatch.setattr(os, "fdopen", real_fdopen)
    # at the bound exactly: read
    exact = tmp_path / "exact.bin"
    exact.write_bytes(b"x" * 100)
    assert read_bounded(exact, 100) == b"x" * 100
    # /proc reports 0 bytes: the bound while reading refuses it
    status = Path("/proc/self/status")
    if status.exists():
        assert status.stat().st_size == 0
        with pytest.raises(UntrustedInputError, match=r"status is larger than 10 bytes, the most socnav reads from "
                                                      r"such a file$"):
            read_bounded(status, 10)


def test_pedestrians_per_file_are_bounded(tmp_path, monkeypatch):
    path = tmp_path / "many.txt"
    path.write_text("".join(f"0 {ped} 0 0\n" for ped in range(50)))
    monkeypatch.setattr(trajectories, "MAX_PEDESTRIANS", 49)
    with pytest.raises(replay.TrajectoryFileError, match=rf"{path} holds 50 pedestrians, more than the 49"):
        replay.read_trajectories(path)


def test_a_file_of_many_blocks_reads_as_one(tmp_path, monkeypatch):
    """Block by block parsing (numpy's parser, the line scan for a block it refuses) gives the rows and the line
    numbers the whole file would."""
    rows = "".join(f"{10 * (i // 4)}\t{i % 4}.0\t{i * 0.01:.2f}\t-1.5{'  # c' if i % 9 == 0 else ''}\n"
                   + ("\n# comment\n" if i % 11 == 0 else "") for i in range(2000))
    path = tmp_path / "rows.txt"
    path.write_text(rows.replace("\t1.0\t1.00\t", "\t1.0\t1_0.0\t"))  # one value numpy does not read, Python does
    whole = replay.read_trajectories(path)
    monkeypatch.setattr(trajectories, "_BLOCK_BYTES", 1000)
    blocks = replay.read_trajectories(path)
    assert np.array_equal(np.concatenate(whole.positions), np.concatenate(blocks.positions))
    assert np.array_equal(np.concatenate(whole.samples), np.concatenate(blocks.samples))
    assert 10.0 in np.concatenate(blocks.positions)[:, 0]
    last = rows.count("\n") + 1
    previous = 1 + next(number for number, line in reversed(list(enumerate(rows.split("\n"))))
                        if line.startswith("4990\t1.0"))
    bad = tmp_path / "bad.txt"
    bad.write_text(rows + "0 1 x 0\n")
    with pytest.raises(replay.TrajectoryFileError, match=rf"line {last}: x is not a number: 'x'"):
        replay.read_trajectories(bad)
    bad.write_text(rows + "5 1 0 0\n")
    with pytest.raises(replay.TrajectoryFileError, match=rf"line {last}: frame 5 of pedestrian 1 does not come after "
                                                         rf"its frame 4990 on line {previous}"):
        replay.read_trajectories(bad)


def test_wall_coordinates_are_bounded_in_metres(tmp_path):
    for value in (1e308, -2e6, MAX_COORDINATE * (1 + 1e-15)):
        shown = re.escape(f"{value:g}")
        with pytest.raises(MapError, match=rf"walls\[0\]: vertex 1 has x = {shown} m, beyond the bound of 1e\+06 m"):
            validate_polygons([[[0.0, 0.0], [value, 0.0]]], name="walls")
    assert len(validate_polygons([[[0.0, -MAX_COORDINATE], [MAX_COORDINATE, 0.0]]])) == 1
    with pytest.raises(ConfigError, match=r"obstacles\[0\]: vertex 0 has y = 1e\+07 m, beyond the bound"):
        load_config({"obstacles": [[[0.0, 1e7], [1.0, 1.0]]]})
    map_file = tmp_path / "far.yaml"
    map_file.write_text("obstacles:\n  - [[0, 0], [1.0e+9, 0]]\n")
    with pytest.raises(MapError, match=r"far.yaml: obstacles\[0\]: vertex 1 has x = 1e\+09 m"):
        maps.load_map(map_file)


def test_vertex_counts_are_checked_before_any_geometry(monkeypatch):
    monkeypatch.setattr(maps, "LinearRing", lambda *args: pytest.fail("geometry before the counts"))
    square = [[0, 0], [1, 0], [1, 1], [0, 1]]
    with pytest.raises(MapError, match=r"walls: at least 4098 vertices in all, more than the bound of 4096"):
        validate_polygons([square] * 1366, name="walls")
    with pytest.raises(MapError, match=r"walls\[0\]: 600 vertices, more than the bound of 512 per polygon"):
        validate_polygons([[[i, i * i] for i in range(600)]], name="walls")


def test_a_navigator_with_a_wall_at_1e308_metres_is_refused(tmp_path):
    """The wall bound of a navigator file (format 3), checked by the runtime's schema -- the one export validates
    its metadata with before it writes anything."""
    from pydantic import ValidationError

    from socnav.runtime.format import NavigatorMetadata

    with pytest.raises(ValidationError) as error:
        NavigatorMetadata.model_validate({"walls": [[[0.0, 0.0], [1e308, 0.0]]]})
    walls = [item for item in error.value.errors() if item["loc"] == ("walls",)]
    assert len(walls) == 1 and walls[0]["msg"] == ("Value error, walls[0]: vertex 1 has x = 1e+308 m, beyond the "
                                                  "bound of 1e+06 m from the origin"), error.value


def test_the_limits_page_states_every_limit():
    page = (REPO / "docs" / "limits.md").read_text()
    for value in (replay.MAX_FILE_BYTES, replay.MAX_TOTAL_BYTES, replay.MAX_LINES, replay.MAX_LINE_BYTES,
                  replay.MAX_PEDESTRIANS, replay.MAX_SAMPLES, YAML_MAX_BYTES, YAML_MAX_NODES, maps.MAX_MAP_BYTES,
                  maps.MAX_IMAGE_BYTES, maps.MAX_GRID_CELLS, maps.MAX_TOTAL_VERTICES, maps.MAX_POLYGON_VERTICES):
        assert f"{value:,}" in page, value
    assert f"{YAML_MAX_DEPTH} levels" in page and re.search(r"10\^6 m|1,000,000 m", page)
    assert "limits.md" in (REPO / "mkdocs.yml").read_text()
