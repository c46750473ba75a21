"""Benchmark scripts (run as files); a package so one script can reuse another's peers."""
