"""Does the config's channel hold still in free space on a clean link? (issue 23)

The unfiltered wave channel (``channel.wave_filter_hz: null``) is lossless: in free space the
TO reflects every wave (Z_t = 0, Gamma_t = 1), so the chain's damping is the HSI's alone, and at
short delays the sampled HSI termination feeds a ringing mode that grows until the torque
saturates and the safety layer stops on tracking error (measured: D = 1 ms stops within 0.4 s
at b = 5, 1.6 s at b = 1; D = 5 ms within 8 s; D = 20 ms at b = 5). Which (b, D) ring depends
on the HSI's discrete dynamics and the delay's phase, so ``check`` does not guess it: it runs
the config once with no environment and no impairment (fast mode, simulated robots, at most
``PROBE_S`` seconds, the operator moving back and forth) and refuses the config if that run
ends in a safety stop. Only for the unfiltered wave channel behind a delay: every other channel
and the filtered wave channel skip the probe.
"""

from __future__ import annotations

from teleop_rt.config import SessionConfig, Waypoint

PROBE_S = 10.0  # the measured stops come within 8 s


def needs_probe(cfg: SessionConfig) -> bool:
    ch = cfg.channel
    return ch.mode == "wave" and cfg.delay_ticks > 0 and ch.wave_filter_hz is None


def free_space_stop(cfg: SessionConfig) -> str | None:
    """The safety stop of the config's channel in free space on a clean link (None: none, or
    no probe needed): the operator's first two waypoints, alternated every second."""
    from teleop_rt.session import Session

    if not needs_probe(cfg):
        return None
    update: dict = {"environment": [], "duration_s": PROBE_S, "backend": "sim",
                    "link": cfg.link.model_copy(update={"impairment": None}),
                    "hsi": cfg.hsi.model_copy(update={"backend": None}),
                    "to": cfg.to.model_copy(update={"backend": None})}  # fmt: skip
    wps = getattr(cfg.operator, "waypoints", None)
    if wps and len(wps) >= 2:
        a, b = wps[0].position_m, wps[1].position_m
        sweep = [Waypoint(t_s=0.5 + k, position_m=a if k % 2 == 0 else b)
                 for k in range(int(PROBE_S))]  # fmt: skip
        update["operator"] = cfg.operator.model_copy(update={"waypoints": sweep})
    probe = cfg.model_copy(update=update)
    summary = Session(probe).run()
    return summary.stopped_early if summary.safety_stop else None
