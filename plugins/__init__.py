"""The Mitsuba plugins of mitsuba-pbrt-tex, one per module (installed as
``mitsuba_pbrt_tex.plugins``).

Each module starts with a docstring whose table lists the plugin's parameters (name, type, default,
meaning, differentiable); ``python -m mitsuba_pbrt_tex info`` and the README's plugin table are
generated from those tables. Each module defines ``Plugin``, a plain Python class that
:func:`mitsuba_pbrt_tex.register` turns into a Mitsuba plugin for the current variant.
"""
