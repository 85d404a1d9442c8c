"""The host under the backends: clocks, the cyclic loop, timing statistics, real-time set-up, capabilities, allocation checks."""
