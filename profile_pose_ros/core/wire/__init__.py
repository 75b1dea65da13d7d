"""Bytes on the wire: CDR for the ROS messages the hot path serializes itself, the profiler, trigger MCU
and MotoPlus protocols."""
