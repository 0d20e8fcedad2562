"""docs/foxglove_layout.json: what teleop_rt.recording.layout makes, and every panel's topics
and plotted fields are ones a log has."""

from __future__ import annotations

import json
import re

from conftest import ROOT

from teleop_rt.recording.layout import JOINTS, layout_text
from teleop_rt.recording.scene import ENVIRONMENT, HAND_TARGET, ROBOT_DESCRIPTION
from teleop_rt.recording.schema import LogLayout

LAYOUT = ROOT / "docs" / "foxglove_layout.json"
PATH = re.compile(r"^(/\w+)\.(\w+)(?:\[(\d+)\])?(\.@negative)?$")


def test_the_shipped_layout_is_the_generated_one():
    assert LAYOUT.read_text() == layout_text()


def test_every_plotted_path_is_a_field_of_the_log():
    layout = json.loads(LAYOUT.read_text())
    topics = {t.name: {f.name: f for f in t.fields} for t in LogLayout(JOINTS, 2).topics}
    plotted = 0
    for config in layout["configById"].values():
        for series in config.get("paths", []):
            found = PATH.match(series["value"])
            assert found, series["value"]
            topic, name, index, _ = found.groups()
            field = topics[topic][name]
            assert (index is None) == (field.length is None), series["value"]
            assert index is None or int(index) < field.length, series["value"]
            plotted += 1
    assert plotted >= 12


def test_panels_and_the_tree_agree():
    layout = json.loads(LAYOUT.read_text())
    three_d = layout["configById"]["3D!teleop"]
    assert set(three_d["topics"]) == {ROBOT_DESCRIPTION, ENVIRONMENT, HAND_TARGET}
    used = []

    def walk(node):
        if isinstance(node, str):
            used.append(node)
        else:
            walk(node["first"])
            walk(node["second"])

    walk(layout["layout"])
    assert sorted(used) == sorted(layout["configById"])
