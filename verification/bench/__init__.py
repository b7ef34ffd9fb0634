"""Benchmarks (``make bench``): the engine against scipy and its peers, the reference's solves, the
roofline of this machine and what the hot loops compile to. Speed is measured here, never in tests."""
