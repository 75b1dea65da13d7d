"""Designing and checking gauges: random and height-field gauges, the Cramer-Rao bounds, rule checks and
the gauge search."""
