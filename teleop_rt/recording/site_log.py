"""A site's own log (``teleop-rt site``): its robot, its port, the peer's packets it used, its
timing; written by the same recorder and writer as a session's log (``Recorder``), so the
same rules hold: the tick only copies a row into the ring, a full ring drops and counts,
a dead or failing writer is noticed, closing is bounded, an incomplete log is exit code 4.

Topics (``LogLayout(site=...)``): the site's robot as in a session's log (``/hsi`` or
``/to``), ``/port`` (its port under the paper's names), ``/link`` (per tick: the peer's packet
used, or none, with its sender tick, the tick it arrived at, its one-way delay and the coupling
state it carried), ``/timing``,
and the 3D topics of its robot alone, placed where a session's log places it (two site logs
opened together show both robots as one session's log does). Metadata beyond a session's:
log_kind "site", site, config_hash (what both sites share) and, once the handshake is done
(``Recorder.describe``), session_id; log times count from the instant both sites agreed to
start at, so tick k of the HSI's log and of the TO's is the same instant.

Paths: ``--log out.mcap`` on ``teleop-rt run --link zenoh`` gives the sites ``out.hsi.mcap``
and ``out.to.mcap`` (``site_log_path``); by default ``logs/<name>-<UTC time>.<site>.mcap``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from teleop_rt.com.zenoh_link import Arrival, shared_parts
from teleop_rt.declarations import SITES
from teleop_rt.flat import Packed
from teleop_rt.recording.recorder import (
    DEFAULT_LOG_DIR,
    LogParts,
    Recorder,
    _attachments,
    _metadata,
    _shape,
    default_log_path,
    mapping_metadata,
    robot_columns,
)
from teleop_rt.recording.scene import scene_spec, shift_sources
from teleop_rt.recording.schema import LogLayout
from teleop_rt.site import Site

if TYPE_CHECKING:
    from teleop_rt.recording.live import LiveAddress
    from teleop_rt.session import Session

class SiteLogSource:
    """What the recorder reads of a site that runs alone. Building it packs the site's blocks
    and an ``Arrival`` (what the link fills in at every receive) into one buffer, the row's
    only source."""

    def __init__(self, site: Site) -> None:
        self.site, self.cfg, self.n, self.dt = site, site.cfg, site.n, site.dt
        self.name = site.name
        setattr(self, site.name, site)  # as a session has it (scene_spec, shift_sources)
        self.arrival = Arrival()
        self.packed = Packed([*site.blocks, self.arrival])
        site.bind(self.packed, 0)

    @property
    def tick(self) -> int:
        return self.site.tick

    def log_parts(self) -> LogParts:
        site, cfg = self.site, self.cfg
        n_env = len(cfg.environment) if self.name == "to" else 0
        # the port of its size, the robot with its joints; a mapped site's map too
        joints = {"n_hsi" if self.name == "hsi" else "n_to": site.n}
        layout = LogLayout(site.port.n, n_env, self.name, **joints,
                           mapped=bool(site.mapping.active))  # fmt: skip
        robot, port, link = layout.topics[:3]
        out = robot_columns(self.packed, site, robot)
        # /port and /link: each field from the block field it is declared to log (Logged)
        owners = {"port": site.port, "packet": site.rx, "arrival": self.arrival}
        for field in (*port.fields[2:], *link.fields[2:]):
            assert field.source is not None  # (every field of these topics is declared so)
            owner, attr = field.source
            out += self._columns(owners[owner], attr, field.count)
        # to the session's helpers this is a session: cfg, n, dt, tick, the site under its name
        as_session = cast("Session", self)
        shifts = shift_sources(as_session) if n_env else np.zeros(0, dtype=np.int64)
        meta = {
            **_metadata(as_session),
            "joints": str(layout.n),  # (the port's size, as a session's log has it)
            "env_elements": str(n_env),
            "log_kind": "site",
            "site": self.name,
            "config_hash": shared_parts(cfg, self.n)["config_hash"],
            **_shape(layout),
            **mapping_metadata(cfg, layout, [site]),
        }
        return LogParts(
            layout, np.array(out, dtype=np.int64), shifts, meta, _attachments(as_session),
            scene_spec(as_session, (self.name,)),
        )  # fmt: skip

    def _columns(self, block, attr: str, count: int) -> list[int]:
        first = self.packed.index_of(block, attr)
        return list(range(first, first + count))


def site_recorder(
    site: Site,
    path: Path,
    wait_for_room: bool = False,
    metadata: dict[str, str] | None = None,
    live: LiveAddress | None = None,
) -> Recorder:
    """The recorder of a site's own log at ``path``, for ``teleop-rt site`` (over the network:
    never waits for room) and for ``teleop-rt replay SITE.mcap`` (fast mode, simulated:
    ``wait_for_room``, no row lost); ``live``: serve it too (``--live``)."""
    return Recorder(SiteLogSource(site), path, wait_for_room=wait_for_room, metadata=metadata,
                    live=live)  # fmt: skip


def site_log_path(base: str | Path, site: str) -> Path:
    """The log of ``site`` for a two-site run logging to ``base``: ``out.mcap`` gives
    ``out.hsi.mcap`` / ``out.to.mcap``; a path without ``.mcap`` gets ``.<site>.mcap`` added."""
    base = Path(base)
    if base.suffix == ".mcap":
        return base.with_suffix(f".{site}.mcap")
    return base.with_name(f"{base.name}.{site}.mcap")


def default_pair_base(name: str, directory: Path | None = None) -> Path:
    """logs/<name>-<UTC time>.mcap such that neither site's log exists (numbered if needed)."""
    directory = DEFAULT_LOG_DIR if directory is None else directory
    base = default_log_path(name, directory)
    i = 1
    while any(site_log_path(base, s).exists() for s in SITES):
        base = default_log_path(f"{name}-{i}", directory)
        i += 1
    return base
