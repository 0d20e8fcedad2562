"""Reference figures of every config in configs/ at 0 and 50 ms, recorded from main before the
two-sites restructure (issue 15) and kept in tests/data/reference_figures.json: the summary's
T_p, T_tau and channel energy, and per logged field a SHA-256 of its exact bytes (bit-for-bit
identity) with its sum and sum of squares (for the fields whose arithmetic changed).

    python -m tests.reference_figures          # rewrite the reference (only on purpose)
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from teleop_rt import config
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.session import Session

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "tests" / "data" / "reference_figures.json"
DELAYS_MS = (0, 50)
# CAN configs run on the simulated backend here: the emulated drives add a tick of command delay
# and are compared against the sim backend by tests/test_can_session.py
OVERRIDES = {"can_emulated": ["backend=sim"]}


def configs() -> list[Path]:
    return sorted((ROOT / "configs").glob("*.yaml"))


def figures(path: Path, delay_ms: int) -> dict:
    """Run ``path`` at ``delay_ms`` in fast mode with recording; its figures."""
    overrides = [*OVERRIDES.get(path.stem, []), f"channel.delay_ms={delay_ms}"]
    cfg = config.load(path, overrides)
    with tempfile.TemporaryDirectory() as tmp:
        log_path = Path(tmp) / "ref.mcap"
        session = Session(cfg)
        summary = session.run(recorder=Recorder(session, log_path))
        log = read_log(log_path, topics=["/hsi", "/to", "/channel"])
    fields = {}
    for topic in log.layout.topics[:3]:
        data = log.topics[topic.name]
        for field in topic.fields:
            values = np.ascontiguousarray(data[field.name])
            x = values.astype(np.float64)
            fields[f"{topic.name}.{field.name}"] = {
                "sha256": hashlib.sha256(values.tobytes()).hexdigest(),
                "sum": float(x.sum()),
                "sum_sq": float((x * x).sum()),
            }
    return {
        "ticks": summary.ticks,
        "t_p": summary.t_p,
        "t_tau": summary.t_tau,
        "channel_energy_j": summary.channel_energy_j,
        "min_channel_energy_j": summary.min_channel_energy_j,
        "fields": fields,
    }


def cases() -> list[tuple[Path, int]]:
    return [(path, d) for path in configs() for d in DELAYS_MS]


def key(path: Path, delay_ms: int) -> str:
    return f"{path.stem}@{delay_ms}ms"


def main() -> int:
    out = {}
    for path, delay in cases():
        print(f"{key(path, delay)} ...", file=sys.stderr, flush=True)
        out[key(path, delay)] = figures(path, delay)
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    REFERENCE.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"wrote {REFERENCE}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
