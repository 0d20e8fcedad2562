"""The Foxglove layout shipped as ``docs/foxglove_layout.json`` (the app's export format, for its
"Import from file..."): the 3D panel with both robots, and plots of q_h against q_t, tau_h against
tau_e, the channel's energy and the tick's timing, for a session of two joints.

``python -m teleop_rt.recording.layout docs/foxglove_layout.json`` writes it again; a test
keeps the file equal to what this makes, and every plotted field a field of the log.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from teleop_rt.recording.scene import ENVIRONMENT, HAND_TARGET, ROBOT_DESCRIPTION, WORLD

JOINTS = 2
HSI_COLOR, TO_COLOR = "#3373d9", "#e6802a"  # as the robots in 3D (scene.COLORS)


def _series(value: str, label: str, color: str, dashed: bool = False) -> dict:
    return {
        "value": value,
        "enabled": True,
        "timestampMethod": "receiveTime",
        "label": label,
        "color": color,
        **({"lineStyle": "dashed"} if dashed else {}),
    }


def _plot(title: str, paths: list[dict]) -> dict:
    return {
        "foxglovePanelTitle": title,
        "paths": paths,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": False,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 240,
    }


def _pairs(hsi: str, to: str, label_h: str, label_t: str) -> list[dict]:
    """One HSI and one TO series per joint; the HSI dashed, as in ``teleop-rt plot``."""
    out = []
    for j in range(JOINTS):
        out.append(_series(hsi.format(j=j), label_h.format(j=j), HSI_COLOR, dashed=j > 0))
        out.append(_series(to.format(j=j), label_t.format(j=j), TO_COLOR, dashed=j > 0))
    return out


def foxglove_layout() -> dict:
    three_d = {
        "foxglovePanelTitle": "HSI (blue) and TO (orange)",
        "followTf": WORLD,
        "followMode": "follow-none",
        "scene": {"transforms": {"showLabel": False, "enablePreloading": True}},
        "transforms": {},
        "topics": {t: {"visible": True} for t in (ROBOT_DESCRIPTION, ENVIRONMENT, HAND_TARGET)},
        "layers": {
            "grid": {
                "layerId": "foxglove.Grid",
                "instanceId": "grid",
                "label": "Grid",
                "visible": True,
                "frameLocked": True,
                "frameId": WORLD,
                "size": 2,
                "divisions": 20,
                "lineWidth": 1,
                "color": "#248eff40",
                "position": [0, 0, 0],
                "rotation": [0, 0, 0],
                "order": 1,
            }
        },
        "cameraState": {
            "perspective": True,
            "distance": 1.6,
            "phi": 40,
            "thetaOffset": 90,
            "target": [0.25, 0, 0.1],
            "targetOffset": [0, 0, 0],
            "targetOrientation": [0, 0, 0, 1],
            "fovy": 45,
            "near": 0.01,
            "far": 100,
        },
        "imageMode": {},
    }
    panels = {
        "3D!teleop": three_d,
        "Plot!q": _plot(
            "joint angles q_h (HSI) vs q_t (TO), rad",
            _pairs("/hsi.q[{j}]", "/to.q[{j}]", "q_h[{j}]", "q_t[{j}]"),
        ),
        "Plot!tau": _plot(
            "torques tau_h (operator on HSI) vs tau_e (TO on environment), N m",
            _pairs("/hsi.tau_ext[{j}]", "/to.tau_ext[{j}].@negative", "tau_h[{j}]", "tau_e[{j}]"),
        ),
        "Plot!energy": _plot(
            "channel energy, J (passive while >= 0)",
            [
                _series("/channel.total_energy", "total", "#2a9d5c"),
                *(
                    _series(f"/channel.energy[{j}]", f"joint {j}", "#7f7f7f", dashed=j > 0)
                    for j in range(JOINTS)
                ),
            ],
        ),
        "Plot!timing": _plot(
            "tick compute time and deadline lateness, ns",
            [
                _series("/timing.compute_ns", "compute", "#7b4fc9"),
                _series("/timing.lateness_ns", "lateness", "#c94f7b"),
            ],
        ),
    }
    plots = {
        "first": {"first": "Plot!q", "second": "Plot!tau", "direction": "column"},
        "second": {"first": "Plot!energy", "second": "Plot!timing", "direction": "column"},
        "direction": "column",
        "splitPercentage": 60,
    }
    return {
        "configById": panels,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": {
            "first": "3D!teleop",
            "second": plots,
            "direction": "row",
            "splitPercentage": 50,
        },  # fmt: skip
    }


def layout_text() -> str:
    return json.dumps(foxglove_layout(), indent=2) + "\n"


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m teleop_rt.recording.layout OUT.json", file=sys.stderr)
        return 2
    Path(argv[0]).write_text(layout_text())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main(sys.argv[1:]))
