"""Scenario files: what is read, and errors that name the file, the line and the field."""
from __future__ import annotations

from pathlib import Path

import pytest

from omnire_sim import ScenarioError, load_scenario, parse_scenario

FULL = """\
# a comment
[camera]
path = "interpolated"
fps = 20
start = 0.5
end = 3.0
cameras = ["front_camera"]   # one camera
width = 480
height = 270
scene_speed = 0.5
[[camera.lane_shift]]
offset = 2.0
start = 1.0
end = 2.0

[output]
video = true
depth = true
crf = 20

[[actor]]
track = "a"
remove = true

[[actor]]
track = "b"
stop_at = 2.5
brake = 1.5
offset = [0.0, 1.0, 0.0]
yaw = 10

[[actor]]
track = "p"
trajectory = [
  {t = 0.5, x = 30.0, y = 8.0},
  {t = 6.0, x = 30.0, y = -8.0, z = 0.9},
]
motion = "gait"
gait_cycle = 1.2

[[insert]]
id = "guest"
run = "../other"
track = "c"
trajectory = [[0.0, 12.0, -3.5, 0.8], [4.0, 40.0, -3.5, 0.8]]
speed = 0.8
"""


def test_full_scenario_is_read(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(FULL)
    s = load_scenario(path)
    assert s.camera.path == "interpolated" and s.camera.fps == 20 and s.camera.cameras == ("front_camera",)
    assert s.camera.lane_shifts[0].offset == 2.0 and s.camera.scene_speed == 0.5
    assert s.output.depth and s.output.crf == 20
    a, b, p = s.actors
    assert a.remove and b.clock.stop_at == 2.5 and b.clock.brake == 1.5 and b.placement.offset == (0.0, 1.0, 0.0)
    assert p.trajectory.waypoints[1].z == 0.9 and p.trajectory.waypoints[0].z is None and p.motion.cycle == 1.2
    ins = s.inserts[0]
    assert ins.track == "c" and ins.clock.speed == 0.8 and len(ins.trajectory.waypoints) == 2
    assert s.resolve_path(ins.run) == tmp_path.resolve() / "../other"
    assert b.where.of("stop_at") == f"{path} line 27, [[actor]] #2, field 'stop_at'"


def test_empty_scenario():
    s = parse_scenario("")
    assert not s.actors and not s.inserts and s.camera.path == "recorded"


def test_waypoints_walked_at_a_speed():
    s = parse_scenario('[[actor]]\ntrack = "p"\ntrajectory = [{x = 0, y = 0}, {x = 3, y = 4}]\npath_speed = 2.5\n'
                       'path_start = 1.0\n')
    assert list(s.actors[0].trajectory.times()) == [1.0, 3.0]


@pytest.mark.parametrize("text, line, needles", [
    ('[[actor]]\ntrack = "a"\nremove = tru\n', 3, ["not valid TOML"]),
    ('[[actor]]\ntrack = "a"\n\nspeeed = 2\n', 4, ["field 'speeed'", "unknown field"]),
    ('[[actor]]\ntrack = "a"\noffset = [1, 2]\n', 3, ["field 'offset'", "3 finite numbers"]),
    ('[[actor]]\ntrack = "a"\nstop_at = "soon"\n', 3, ["field 'stop_at'", "seconds"]),
    ('\n[[actor]]\ntrack = "a"\ntrajectory = [{t = 1, x = 0, y = 0}, {t = 1, x = 1, y = 0}]\n', 4,
     ["trajectory", "must increase"]),
    ('[[actor]]\ntrack = "a"\ntrajectory = [{t = 1, x = 0}]\n', 3, ["trajectory[1]", "missing 'y'"]),
    ('[[actor]]\ntrack = "a"\ntrajectory = [[0, 1]]\n', 3, ["trajectory[1]", "[t, x, y]"]),
    ('[[actor]]\ntrack = "a"\ntrajectory = [{x = 0, y = 0}, {x = 1, y = 0}]\n', 3, ["speed"]),
    ('[[actor]]\ntrack = "a"\nremove = true\nyaw = 3\n', 3, ["removed actor"]),
    ('[[actor]]\ntrack = "a"\nresume_at = 2\n', 3, ["resume_at", "needs 'stop_at'"]),
    ('[[actor]]\ntrack = "a"\nspeed = -1\n', 3, ["field 'speed'", ">= 0"]),
    ('[[actor]]\ntrack = "a"\n[[actor]]\ntrack = "a"\nremove = true\n', 4, ["edited twice"]),
    ('[camera]\npath = "interpolated"\n', 1, ["[camera]", "needs 'fps'"]),
    ('[camera]\npath = "orbit"\n', 2, ["field 'path'", "'recorded'"]),
    ('[camera]\n[[camera.lane_shift]]\noffset = 2\nstart = 3\nend = 1\n', 5, ["field 'end'", "before start"]),
    ('[[insert]]\nid = "g"\nrun = "r"\ntrack = "c"\n', 1, ["exactly one of 'trajectory' or 'replace'"]),
    ('[output]\ncrf = 99\n', 2, ["field 'crf'", "0..51"]),
    ('[[actor]]\ntrack = "a"\nmotion = "gait"\nmotion_fps = 0\n', 4, ["field 'motion_fps'"]),
    ('walk = 1\n', 1, ["field 'walk'"]),
])
def test_errors_name_line_and_field(text, line, needles):
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text, "s.toml")
    msg = str(err.value)
    assert f"line {line}" in msg, msg
    for needle in needles:
        assert needle in msg, msg


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="scenario file not found"):
        load_scenario(tmp_path / "none.toml")


def test_where_survives_comments_and_multiline_values():
    text = "[[actor]] # first\ntrack = \"a\"\ntrajectory = [\n  [0, 1, 2],\n  [1, 2, 2],\n]\nyaw = [1]\n"
    with pytest.raises(ScenarioError, match="line 7.*field 'yaw'"):
        parse_scenario(text, "s.toml")


def test_docs_example_parses():
    docs = Path(__file__).resolve().parents[3] / "docs" / "simulation.md"
    if not docs.is_file():
        pytest.skip("docs/simulation.md not present")
    blocks = docs.read_text().split("```toml\n")[1:]
    assert blocks, "docs/simulation.md has no toml example"
    for block in blocks:
        parse_scenario(block.split("```")[0], "docs/simulation.md")
