"""The gauge, rotations, poses and the profiler's view of the gauge: what every other room builds on."""
