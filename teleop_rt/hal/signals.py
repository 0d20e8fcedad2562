"""The signal blocks between a backend and its site: what a backend measures each tick
(``Feedback``) and what a simulated world knows at the read (``WorldSnapshot``); the compiled
kernels index them by their ``idx`` (``teleop_rt.flat``). The bottom of the HAL: it imports no
backend, no interface and no registry, so a kernel module can index these blocks without
importing any of them."""

from __future__ import annotations

from teleop_rt.flat import Block, Int, Vector, float_view


class Feedback(Block):
    """What a backend measures each tick (SI, joint space), preallocated: ``q``, ``v`` and
    ``tau_ext`` (the torque the outside world applies to the robot, see teleop_rt.control),
    float64 views a backend fills, and ``age_ticks``: ticks since the sensors last delivered
    (0: fresh this tick). The ``*_mv`` memoryviews of the same memory take element writes and
    buffer copies at a fraction of numpy's per-call cost."""

    q = Vector("joint angles, rad")
    v = Vector("joint velocities, rad/s")
    tau_ext = Vector("torque the outside applies to the robot, N m")
    age_ticks = Int("ticks since the sensors last delivered (0: fresh)")
    inputs = Int("the operator's live digital inputs: INPUT_CLUTCH | INPUT_PRESENT bits")

    def _bind(self) -> None:
        super()._bind()
        self.q_mv, self.v_mv, self.tau_mv = (
            float_view(x) for x in (self.q, self.v, self.tau_ext)
        )

    def copy_arrays(self, q: memoryview, v: memoryview) -> None:
        """q, v = q, v given as float64 memoryviews of n entries (a memcpy each)."""
        self.q_mv[:] = q
        self.v_mv[:] = v


# the bits of ``inputs`` (a backend with digital inputs sets them: teleop_rt.hal.can, 0x60FD)
INPUT_CLUTCH, INPUT_PRESENT = 1, 2


class WorldSnapshot(Block):
    """What a simulated world knows at the tick's read (zeros for real hardware): the operator's
    hand reference and force (HSI) or the environment force and contacts (TO: 1.0 in contact),
    for logging and replay. Vectors of 3 in the world frame, SI units (a kernel finds vector k
    at ``3 k``, the contacts at ``3 idx.N_VECTORS``)."""

    reference = Vector("the operator's hand reference, m")
    reference_velocity = Vector("its velocity, m/s")
    force = Vector("operator force on the HSI tool, or environment force on the TO's, N")

    def __init__(self, n_contacts: int = 0) -> None:
        super().__init__(3, tail=n_contacts)

    def _bind_tail(self) -> None:
        self.contacts = self.f[self.tail_start :]
        # for a backend's element writes each tick (cheaper than numpy's)
        self.reference_mv, self.reference_velocity_mv, self.force_mv, self.contacts_mv = (
            float_view(x)
            for x in (self.reference, self.reference_velocity, self.force, self.contacts)
        )
