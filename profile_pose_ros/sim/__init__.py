"""sim_cell: the simulated cell (profiler, trigger MCU, robot controller) behind the real interfaces."""
