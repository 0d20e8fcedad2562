"""A site's tick, declared once: its stages in order, with what each reads and writes, and the
orders every build of a tick derives from them.

The list is the stack's one statement of the order (as Drake declares a system's ports and a
Diagram derives the evaluation order: Tedrake and the Drake Development Team, "Drake: Model-based
design and verification for robotics", 2019; or as ros2_control's controller manager owns the
read → update → write cycle: Chitta et al., "ros_control: A generic and simple control
framework for ROS", JOSS 2(20), 2017). The builds:

- a site alone (``Site.sense`` then ``Site.update``, against any ``Link``): ``alone()``;
- the lock-step session (``Session.step`` around ``teleop_rt.lockstep``'s two kernels), and
  the fused simulated pair (``teleop_rt.lockstep_fused``, the plants' read and write inside
  the kernels): ``lockstep()``;
- two sites over a link stepped from Python (``Session._step_over``, an impaired link):
  ``phased()``;
- the standalone two-port (``teleop_rt.com.channel.two_port_step``, the analysis's COM block):
  ``two_port()``.

The compiled parts stay kernels (a site's kernel holds consecutive stages; a pair's kernels
call them site by site); tests/test_tick_stages.py runs every build with each stage's
``calls`` traced and checks the order against the one derived here, so that an ordering
written by hand in a build cannot drift from this list.
"""

from __future__ import annotations

from typing import NamedTuple

HOST = "host"  # a Python call: the backend, Pinocchio, the workspace box, the task-space map
SITE = "site"  # compiled, in one of the site's kernels (``part``: which)
LINK = "link"  # the link's exchange: a ``Link`` method, or compiled over packed buffers
PAIR = "pair"  # compiled, once for both sites (only where both are in one process)

HSI_NAME, TO_NAME, PAIR_NAME = "hsi", "to", "pair"
PAIR_BLOCKS = ("link", "monitor", "metrics", "pair")
RNEA = "rnea"  # the one value that is no block's: the RNEA torque, between two kernels


class Stage(NamedTuple):
    """One stage of a site's tick."""

    name: str
    runs: str  # HOST, SITE, LINK or PAIR
    part: str  # the site kernel it is in (SITE), else the call's short name
    calls: tuple[str, ...]  # what makes it: "module:function" or "Class.method", per build
    reads: tuple[str, ...]  # blocks (``teleop_rt.site_tick.SITE_ORDER``, PAIR_BLOCKS) or RNEA
    writes: tuple[str, ...]
    doc: str
    when: str = ""  # "": every tick; else the condition a site must meet (``CONDITIONS``)
    two_port: bool = False  # a stage of the standalone two-port (ports and link only)


CONDITIONS = {
    "workspace_box": "the site's guard has a workspace box and is enabled",
    "task_space": "the site's channel couples the tool in the plane (a Jacobian map)",
}

SITE_STAGES: tuple[Stage, ...] = (
    Stage("read", HOST, "read", ("Backend.read", "teleop_rt.hal.sim:sense"),
          (), ("feedback", "world"), "q, v, tau_ext from the backend"),
    Stage("check", SITE, "site_sense", ("teleop_rt.safety:measured_fault",),
          ("feedback", "guard"), (), "every measurement finite and plausible"),
    Stage("port_input", SITE, "site_sense", ("teleop_rt.com.port:port_input",),
          ("feedback", "mapping", "signals"), ("signals", "mapping", "port", "tx"),
          "tau_h or tau_e; the port's input (omega_c = v_h, tau_t = tau_e, or mapped) into "
          "the outgoing packet", two_port=True),
    Stage("send", LINK, "send", ("Link.send",), ("tx",), ("link",),
          "the packet to the link (in packed buffers it already lies where the link reads it)"),
    Stage("deliver", LINK, "receive", ("Link.receive", "teleop_rt.com.exchange:link_exchange"),
          ("link",), ("rx", "port"),
          "the packet due this tick (eq 10), and the codec's look-ahead into the line",
          two_port=True),
    Stage("port", SITE, "site_before_models", ("teleop_rt.com.exchange:port_stage",),
          ("rx", "port"), ("port", "tx", "mapping"),
          "the port (eq 9) between the codec's receive and send: tau_c or omega_t, the wave",
          two_port=True),
    Stage("controller", SITE, "site_before_models", ("teleop_rt.control:pid_step",),
          ("signals", "port", "feedback", "mapping"), ("signals", "controller"),
          "the error (tau_h - tau_c or omega_t - v_t), C1 or C2 (eq 4, 14): a_ref"),
    Stage("prepare", SITE, "site_before_models", ("teleop_rt.control:ct_prepare",),
          ("controller",), ("computed_torque",), "M_v^-1 a_ref, the RNEA's acceleration"),
    Stage("push", LINK, "end_tick", ("Link.end_tick", "teleop_rt.com.link:link_push"),
          ("tx",), ("link",), "the complete packet (its wave and energy) may travel",
          two_port=True),
    Stage("monitor", PAIR, "monitor", ("teleop_rt.com.channel:monitor_step",),
          ("port",), ("monitor",), "the two-port's power and energy (eq 7, 8)", two_port=True),
    Stage("rnea", HOST, "rnea", ("pinocchio:rnea",), ("feedback", "computed_torque"), (RNEA,),
          "M(q) M_v^-1 a_ref + n(q, v): one RNEA (Pinocchio)"),
    Stage("workspace", HOST, "workspace", ("RobotGuard.check_workspace",), ("feedback", "guard"),
          (), "the tool inside its workspace box (forward kinematics)", when="workspace_box"),
    Stage("torque", SITE, "site_after_models", ("teleop_rt.control:ct_finish",),
          (RNEA, "feedback", "computed_torque"), ("computed_torque", "signals"),
          "computed torque (eq 2, 12): g = RNEA - tau_ext"),
    Stage("guard", SITE, "site_after_models", ("teleop_rt.safety:guard_site",),
          ("feedback", "computed_torque", "guard"), ("computed_torque", "guard"),
          "the safety checks; the torque saturated at the effort limits"),
    Stage("account", PAIR, "account", ("teleop_rt.transparency_tick:accumulate",),
          ("guard", "mapping", "feedback", "signals"), ("pair", "metrics"),
          "saturated ticks; T_p, T_tau (eq 18)"),
    Stage("write", HOST, "write", ("Backend.write", "teleop_rt.hal.sim:command"),
          ("computed_torque",), (), "the checked torque to the backend"),
    Stage("kinematics", HOST, "kinematics", ("teleop_rt.site:map_tool",),
          ("feedback", "mapping"), ("mapping",),
          "the next tick's Jacobian map at the measured q (one Pinocchio call)",
          when="task_space"),
)  # fmt: skip

STAGES = {stage.name: stage for stage in SITE_STAGES}
SENSE_PHASE = tuple(s.name for s in SITE_STAGES[: [s.name for s in SITE_STAGES].index("send") + 1])
UPDATE_PHASE = tuple(s.name for s in SITE_STAGES if s.name not in SENSE_PHASE)


def _groups() -> list[list[Stage]]:
    """Consecutive stages of one site kernel together (a kernel runs whole, site by site)."""
    groups: list[list[Stage]] = []
    for stage in SITE_STAGES:
        if groups and stage.runs == SITE and groups[-1][-1].runs == SITE and (
            groups[-1][-1].part == stage.part
        ):
            groups[-1].append(stage)
        else:
            groups.append([stage])
    return groups


Step = tuple[str, str]  # (stage, whose: 'hsi', 'to' or 'pair')


def alone(site: str = HSI_NAME) -> list[Step]:
    """A site alone: every stage but the pair's, in order (``sense`` up to ``send``)."""
    return [(s.name, site) for s in SITE_STAGES if s.runs != PAIR]


def lockstep(packed: bool = True) -> list[Step]:
    """Two sites in lock-step: each kernel's stages for the HSI, then for the TO; the link's
    stages once for both where the link is compiled over the packed buffers (``packed``: the
    send is then no call at all), else site by site; the pair's stages once."""
    steps: list[Step] = []
    for group in _groups():
        head = group[0]
        if head.runs == PAIR or (head.runs == LINK and packed):
            if not (head.name == "send" and packed):
                steps.append((head.name, PAIR_NAME))
            continue
        steps += [(s.name, site) for site in (HSI_NAME, TO_NAME) for s in group]
    return steps


def phased() -> list[Step]:
    """Two sites over a link stepped from Python: each site's sense phase, then each site's
    update phase (a link may carry a packet only once both have sent), then the pair's."""
    steps: list[Step] = []
    for phase in (SENSE_PHASE, UPDATE_PHASE):
        for site in (HSI_NAME, TO_NAME):
            steps += [(name, site) for name in phase if STAGES[name].runs != PAIR]
    return steps + [(s.name, PAIR_NAME) for s in SITE_STAGES if s.runs == PAIR]


def two_port() -> list[Step]:
    """The standalone two-port: the lock-step's stages that touch only the ports and link."""
    return [step for step in lockstep(packed=True) if STAGES[step[0]].two_port]


def present(steps: list[Step], meets: dict[str, set[str]]) -> list[Step]:
    """``steps`` without a site's conditional stages it does not meet (``meets``: per site,
    the ``CONDITIONS`` it meets)."""
    return [
        (name, who) for name, who in steps
        if not STAGES[name].when or STAGES[name].when in meets.get(who, set())
    ]  # fmt: skip
