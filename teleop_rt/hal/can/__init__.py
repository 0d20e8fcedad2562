"""CANopen (CiA 301 / CiA 402) support for servo drives in cyclic synchronous torque mode.

``codec`` holds pure, bus-free frame encoders/decoders and unit conversions; ``cia402`` the
power state machine stepped one controlword per tick; ``config`` the ``can:`` config section;
``startup`` the canopen start-up (SDO, EDS, NMT); ``backend`` the CAN backend (registered as
"can"); ``emulator`` the CiA 402 drive emulator used by the tests and tools/drive_emulator.py;
``od/`` the bundled generic CiA 402 EDS. Nothing here is imported eagerly so that importing the
package stays cheap (``cia402``, ``startup``, ``emulator`` pull in canopen, hence python-can).
"""
