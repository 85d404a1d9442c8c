"""Runtime: the cyclic loop, timing statistics, gc control, allocation checks."""
