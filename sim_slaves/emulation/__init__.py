"""The emulators behind :mod:`fieldbus.testing`, registered as entry points ``fieldbus.emulators``.

``ethercat``: the ESC chain in-process (the ``sim`` backend holds it) or the
wire runner on a veth pair; ``canopen`` and ``rawcan``: the CAN simulators in
lockstep with the master on a virtual clock, on python-can's ``virtual`` bus
with their own thread, or in a child process on ``fieldbus_udp``.
"""
