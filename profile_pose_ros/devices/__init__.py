"""Device I/O for the nodes: profiler backends, the trigger MCU link, connection supervision.

Plain Python (sockets, pyserial, ctypes), no rclpy, so each piece is testable on its own.
"""
