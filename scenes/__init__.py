"""Bundled scenes (XML) and the data they use; installed as ``mitsuba_pbrt_tex.scenes``."""
