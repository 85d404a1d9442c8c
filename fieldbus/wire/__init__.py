"""The wire layer: what the product and its emulators both need to speak a bus, below the backends.

- :mod:`.framemaster`: EtherCAT bring-up and SDO access frame by frame (the ``sim`` backend's
  master, the emulators' self-test, SII strings for scans);
- :mod:`.pcap`: EtherCAT captures as pcap files (the backend's ``pcap`` option, the emulator's ``--pcap``);
- :mod:`.sockfilter`: classic BPF filters on packet and UDP sockets;
- :mod:`.canlog`: CAN frames to python-can log files, written by a thread off the cycle.

It imports the pure core (frame codecs, models) and the standard library, never a backend, the
runtime, the network or a command (tests/unit/test_layers.py).
"""
