"""CANopen (CiA 301 / CiA 402) support for servo drives in cyclic synchronous torque mode.

``codec`` holds pure, bus-free frame encoders/decoders and unit conversions; ``cia402`` holds
the power state machine stepped one controlword per tick. Nothing here is imported eagerly so
that importing the package stays cheap (``cia402`` pulls in ``canopen``, hence python-can).
"""
