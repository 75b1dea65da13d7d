"""Clocks and freshness: device-to-host clock maps, stamp-age checks, latency windows, sequence gaps."""
