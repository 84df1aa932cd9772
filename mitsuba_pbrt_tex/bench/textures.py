"""The bundled test textures, generated (not painted) so they are reproducible.

``python -m mitsuba_pbrt_tex.bench.textures [FOLDER]`` writes them (default: the package's
``scenes/textures``); ``tests/test_scenes.py`` checks the committed files against this
description.

* ``checker.png`` — 512×512 8-bit sRGB, 16×16 checks of two colours (an image twin of the
  procedural checkerboard: with ``to_uv`` scaled by 1/16 per check the patterns coincide);
* ``zoneplate.png`` — 512×512 8-bit grey, ``0.5 + 0.5·cos(π r²/512)``: frequency rising
  linearly from the centre to the Nyquist rate at the border, the classic aliasing detector;
* ``grid.png`` — 256×256 8-bit sRGB, thin lines every 16 texels over a colour ramp, for the
  mapping scenes (seams and poles show as broken lines).
"""

from __future__ import annotations

import os
import sys

import numpy as np

CHECK_COLORS = (np.array([230, 225, 210], np.uint8), np.array([40, 60, 110], np.uint8))


def checker(size=512, checks=16) -> np.ndarray:
    cell = size // checks
    y, x = np.mgrid[0:size, 0:size]
    even = ((x // cell) + (y // cell)) % 2 == 0
    return np.where(even[..., None], CHECK_COLORS[0], CHECK_COLORS[1]).astype(np.uint8)


def zoneplate(size=512) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] + 0.5
    r2 = (x - size / 2) ** 2 + (y - size / 2) ** 2
    v = 0.5 + 0.5 * np.cos(np.pi * r2 / size)
    return np.round(v * 255).astype(np.uint8)


def grid(size=256, spacing=16) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size]
    img = np.stack([x / size * 200 + 30, y / size * 200 + 30, np.full_like(x, 120.0)], -1)
    line = (x % spacing == 0) | (y % spacing == 0)
    img[line] = 10
    return np.round(img).astype(np.uint8)


def write_all(folder: str) -> list[str]:
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant('scalar_rgb')
    os.makedirs(folder, exist_ok=True)
    out = []
    for name, img, fmt in (('checker.png', checker(), mi.Bitmap.PixelFormat.RGB),
                           ('zoneplate.png', zoneplate(), mi.Bitmap.PixelFormat.Y),
                           ('grid.png', grid(), mi.Bitmap.PixelFormat.RGB)):
        path = os.path.join(folder, name)
        mi.Bitmap(np.ascontiguousarray(img), fmt).write(path)
        out.append(path)
    return out


def default_folder() -> str:
    from .. import scenes
    return os.path.join(os.path.dirname(scenes.__file__), 'textures')


if __name__ == '__main__':
    import mitsuba_pbrt_tex  # noqa: F401  (LLVM bootstrap before Mitsuba starts)
    for p in write_all(sys.argv[1] if len(sys.argv) > 1 else default_folder()):
        print(p)
