"""Bus scans: what is on a live EtherCAT segment or CAN bus, and drive maps written from it."""
