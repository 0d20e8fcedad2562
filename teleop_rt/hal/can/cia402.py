"""CiA 402 power state machine on the master side, stepped one controlword per tick.

The tables come from ``canopen.profiles.p402.State402`` (statusword masks, controlword
commands, the transition table and the "next state toward OPERATION ENABLED" path) rather than
being retyped here. At import they are compiled into two small lookups so ``step`` is a few
integer operations: no dict walks, no allocation, never a wait.

Quick stop: after ``request_stop`` the stepper sends quick stop (0x02) until the drive reports
SWITCH ON DISABLED, then disable voltage (0x00). A drive leaves QUICK STOP ACTIVE for SWITCH ON
DISABLED by itself only with quick stop option code 0x605A in 1..4; with 5..8 it stays halted
and powered in QUICK STOP ACTIVE, so configure 1..4 (e.g. 2) for CAN sessions.
"""

from canopen.profiles.p402 import State402

NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"
UNKNOWN = "UNKNOWN"  # a statusword that matches no CiA 402 state
_STATES = (
    NOT_READY_TO_SWITCH_ON,
    SWITCH_ON_DISABLED,
    READY_TO_SWITCH_ON,
    SWITCHED_ON,
    OPERATION_ENABLED,
    QUICK_STOP_ACTIVE,
    FAULT_REACTION_ACTIVE,
    FAULT,
)

CW_DISABLE_VOLTAGE = State402.CW_DISABLE_VOLTAGE  # 0x00
CW_QUICK_STOP = State402.CW_QUICK_STOP  # 0x02
CW_SHUTDOWN = State402.CW_SHUTDOWN  # 0x06
CW_SWITCH_ON = State402.CW_SWITCH_ON  # 0x07
CW_ENABLE_OPERATION = State402.CW_OPERATION_ENABLED  # 0x0F
CW_FAULT_RESET = State402.CW_SWITCH_ON_DISABLED  # 0x80: bit 7, acts on its rising edge


def _build_state_lut() -> tuple[str, ...]:
    # Every SW_MASK mask lies within bits 0..6, so the low 7 bits fully decide the state.
    lut = []
    for low7 in range(0x80):
        names = [n for n, (mask, value) in State402.SW_MASK.items() if low7 & mask == value]
        if len(names) > 1:  # canopen's masks are disjoint; refuse to guess if that changes
            raise RuntimeError(f"statusword 0x{low7:02X} matches several states: {names}")
        # Map to this module's constants: fails loudly if canopen ever renames a state.
        lut.append(_STATES[_STATES.index(names[0])] if names else UNKNOWN)
    return tuple(lut)


def _build_toward_enabled() -> dict[str, int]:
    # Controlword that moves each state one transition toward OPERATION ENABLED, read off
    # canopen's path (NEXTSTATE2ANY) and TRANSITIONTABLE; OPERATION ENABLED holds itself.
    table = {OPERATION_ENABLED: CW_ENABLE_OPERATION, UNKNOWN: CW_DISABLE_VOLTAGE}
    for state in State402.SW_MASK:
        nxt = State402.next_state_indirect(state)
        if nxt is not None:
            table[state] = State402.TRANSITIONTABLE[(state, nxt)]
    return table


_STATE_LUT = _build_state_lut()
_TOWARD_ENABLED = _build_toward_enabled()


def decode_statusword(statusword: int) -> str:
    """CiA 402 state name of a statusword 0x6041 (``UNKNOWN`` if it matches none)."""
    return _STATE_LUT[statusword & 0x7F]


class Cia402Stepper:
    """Drives one CiA 402 drive toward OPERATION ENABLED, one controlword per tick.

    Call ``step(statusword)`` once per tick with the latest statusword and send the returned
    controlword. Per state (canopen's tables, CiA 402 transitions in brackets):
    SWITCH ON DISABLED -> shutdown 0x06 [2]; READY TO SWITCH ON -> switch on 0x07 [3];
    SWITCHED ON / OPERATION ENABLED -> enable operation 0x0F [4]; QUICK STOP ACTIVE ->
    disable voltage 0x00 [12]; NOT READY TO SWITCH ON, FAULT REACTION ACTIVE, unknown -> 0x00
    (wait: those transitions are the drive's own); FAULT -> fault reset [15] on a rising edge
    of bit 7: ``reset_low_ticks`` ticks of 0x00, then one tick of 0x80, repeated, so bit 7 is
    never high on two consecutive ticks.

    Parameters:
        reset_low_ticks: ticks of 0x00 before each 0x80 while in FAULT (>= 1); raise it for a
            drive that needs longer between reset attempts.
    """

    __slots__ = ("_controlword", "_low_ticks", "_reset_low_ticks", "_state", "_stop")

    def __init__(self, reset_low_ticks: int = 1) -> None:
        if isinstance(reset_low_ticks, bool) or not isinstance(reset_low_ticks, int):
            raise ValueError(f"reset_low_ticks must be an integer >= 1, got {reset_low_ticks!r}")
        if reset_low_ticks < 1:
            raise ValueError(f"reset_low_ticks must be an integer >= 1, got {reset_low_ticks!r}")
        self._reset_low_ticks = reset_low_ticks
        self._low_ticks = 0  # consecutive ticks with bit 7 low, counted only while in FAULT
        self._state = UNKNOWN
        self._controlword = CW_DISABLE_VOLTAGE
        self._stop = False

    def step(self, statusword: int) -> int:
        """Decode ``statusword`` and return the controlword to send this tick."""
        state = _STATE_LUT[statusword & 0x7F]
        self._state = state
        if self._stop:
            cw = CW_DISABLE_VOLTAGE if state == SWITCH_ON_DISABLED else CW_QUICK_STOP
        elif state == FAULT:
            if self._low_ticks >= self._reset_low_ticks:
                cw = CW_FAULT_RESET
            else:
                cw = CW_DISABLE_VOLTAGE
        else:
            cw = _TOWARD_ENABLED[state]
        # Count low ticks only inside FAULT, so a fresh fault always starts with 0x00.
        low = state == FAULT and not cw & CW_FAULT_RESET
        self._low_ticks = self._low_ticks + 1 if low else 0
        self._controlword = cw
        return cw

    def request_stop(self) -> None:
        """Latch a stop: quick stop (0x02) until SWITCH ON DISABLED, then 0x00, for good."""
        self._stop = True

    @property
    def stop_requested(self) -> bool:
        return self._stop

    @property
    def state(self) -> str:
        """State decoded from the last statusword (``UNKNOWN`` before the first step)."""
        return self._state

    @property
    def controlword(self) -> int:
        """Controlword returned by the last ``step`` (0x00 before the first)."""
        return self._controlword

    @property
    def torque_allowed(self) -> bool:
        """True only if the last statusword was OPERATION ENABLED and no stop was requested.

        Otherwise the target torque sent with the controlword must be zero.
        """
        return self._state == OPERATION_ENABLED and not self._stop
