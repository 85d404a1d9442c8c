"""Running a network and watching it: the live monitor, the soak harness, the end-of-run report (above the network)."""
