"""Writing rendered images: OpenEXR (through the OpenEXR package) and a tone-mapped PNG, atomically.

Both files are first written to a temporary file in the destination folder and then renamed over
the destination, so a crash never leaves a half-written image, and readers never see one. The
temporary file is removed on any exception — the command line turns SIGTERM into one
(:class:`Terminated`) — and the image gets the permissions a newly created file gets under the
user's umask (not the 0600 of the temporary file).
"""

from __future__ import annotations

import os
import re
import signal
import tempfile
import threading

import numpy as np


class Terminated(BaseException):
    """Raised by the SIGTERM handler :func:`terminate_on_sigterm` installs (a BaseException, like
    KeyboardInterrupt, so only cleanup code sees it)."""


def terminate_on_sigterm() -> None:
    """Turn SIGTERM into :class:`Terminated` (main thread), so temporary files are removed."""
    def handler(signum, frame):
        raise Terminated(f'terminated by signal {signum}')
    try:
        signal.signal(signal.SIGTERM, handler)
    except ValueError:             # not the main thread: signals stay as they are
        pass


_umask_lock = threading.Lock()


def _umask() -> int:
    try:                           # Linux ≥ 4.7 reports it without changing it
        with open('/proc/self/status') as f:
            for line in f:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    with _umask_lock:              # elsewhere reading the umask means setting it: set it back
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _atomic(path: str, write) -> None:
    folder = os.path.dirname(os.path.abspath(path)) or '.'
    os.makedirs(folder, exist_ok=True)
    suffix = os.path.splitext(path)[1]
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix='.tmp-', suffix=suffix, dir=folder)
        os.close(fd)
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())       # mkstemp made it 0600
        os.replace(tmp, path)
        tmp = None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def write_exr(path: str, image: np.ndarray, channel_names: list[str] | None = None) -> None:
    """float32 (H, W, C) image; channels named R,G,B[,…] unless given."""
    import OpenEXR
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    names = channel_names or (['R', 'G', 'B'] if image.shape[2] >= 3 else ['Y'])
    names = names + [f'C{i}' for i in range(len(names), image.shape[2])]
    channels = {n: np.ascontiguousarray(image[..., i]) for i, n in enumerate(names)}
    header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}

    def write(tmp):
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)

    _atomic(path, write)


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (clamped; exposure in stops)."""
    x = np.clip(np.nan_to_num(rgb * 2.0 ** exposure, nan=0.0, posinf=1.0, neginf=0.0), 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255), 0, 255).astype(np.uint8)


#: The PNG text entry that marks our renders (``render`` replaces only PNGs that carry it).
_GENERATOR = ('generator', 'mitsuba_pbrt_tex')


def write_png(path: str, rgb: np.ndarray, exposure: float = 0.0) -> None:
    """Tone-mapped 8-bit sRGB PNG, marked as ours (:func:`written_by_us`)."""
    import mitsuba as mi
    img = tonemap(np.asarray(rgb, dtype=np.float64)[..., :3], exposure)
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    bmp = mi.Bitmap(np.ascontiguousarray(img), mi.Bitmap.PixelFormat.RGB)
    bmp.metadata()[_GENERATOR[0]] = _GENERATOR[1]
    _atomic(path, lambda tmp: bmp.write(tmp))


def written_by_us(path: str) -> bool:
    """Does the PNG at ``path`` carry :func:`write_png`'s mark (a tEXt chunk before the image
    data)?"""
    key, value = _GENERATOR
    try:
        with open(path, 'rb') as f:
            head = f.read(1 << 16)
    except OSError:                     # unreadable: not known to be ours
        return False
    # (Mitsuba 3.9 writes the value in quotes)
    return head.startswith(b'\x89PNG') and re.search(
        b'tEXt' + key.encode() + b'\0"?' + value.encode(), head) is not None


def save_figure(fig, path: str, dpi: int) -> None:
    """Lay out, write and close a matplotlib figure (the benchmark and demo charts)."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
