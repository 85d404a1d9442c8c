"""Sans-IO core: no sockets, threads, sleeps or clocks. Time is a parameter."""
