"""The parts of a running network's cycle, each with one job; :class:`fieldbus.Operational` is their façade.

- :mod:`~fieldbus.cycle.status`: what a cycle reports (BusStatus, BusFault, events, CycleResult).
- :mod:`~fieldbus.cycle.buscycle`: one bus's cycle: encode, send, receive, judge, accept, decode, recovery.
- :mod:`~fieldbus.cycle.acyclic`: the SDO queue with futures, drive-fault follow-up reads, diagnostics.
- :mod:`~fieldbus.cycle.stopping`: the safe stop: writers, latch, release, wind-down.
- :mod:`~fieldbus.cycle.motor_events`: the raw-CAN event pump (faults motors report themselves).
"""
