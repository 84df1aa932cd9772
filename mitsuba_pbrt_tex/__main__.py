"""``python -m mitsuba_pbrt_tex``: see :mod:`mitsuba_pbrt_tex.cli`."""

import sys

from .cli import main

sys.exit(main())
