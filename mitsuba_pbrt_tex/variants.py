"""Which Mitsuba variants the plugins support, and the colour type each variant returns.

Supported: the JIT variants (``llvm_*``, ``cuda_*``) in RGB and monochrome flavours, polarized or
not (textures return unpolarized values either way). Refused, at plugin construction and with a
message that says why:

* scalar variants — every lookup is written as vectorised Dr.Jit code (gathers, symbolic loops);
  in scalar variants ``mi.Float`` is a Python ``float`` and Mitsuba calls Python textures once per
  sample, which would be orders of magnitude slower than the built-ins we compete with.
* spectral variants — image textures would need per-texel spectral upsampling *before*
  filtering (upsampling is non-linear, so filtered RGB cannot be upsampled afterwards), and the
  procedural textures compute RGB per lane, which Mitsuba can only upsample from scalar colours.
  Rather than return subtly wrong spectra we refuse.
"""

from __future__ import annotations

import mitsuba as mi


class UnsupportedVariantError(RuntimeError):
    pass


def support_problem(variant: str | None) -> str | None:
    """Why ``variant`` is unsupported, or None when it is supported."""
    if variant is None:
        return 'no Mitsuba variant is set (call mi.set_variant("llvm_ad_rgb") first)'
    why = _unsupported(variant)
    if not why:
        return None
    return '; '.join(why) + '; use %s' % ' or '.join(f'"{v}"' for v in supported_instead(variant))


def _unsupported(variant: str) -> list:
    """Why the plugins refuse ``variant`` (empty where they take it)."""
    why = []
    if variant.startswith('scalar'):
        why.append('scalar variants are not supported: the lookups are vectorised Dr.Jit kernels')
    if 'spectral' in variant:
        why.append('spectral variants are not supported (filtered RGB cannot be spectrally '
                   'upsampled after filtering)')
    return why


def supported_instead(variant: str) -> list:
    """The supported variants closest to ``variant``: its JIT backend (``llvm_ad`` for scalar
    ones) in RGB and mono, polarized if it is — the ones this Mitsuba build has and this
    machine runs; else every variant that works here; else those names."""
    backend = 'cuda_ad' if variant.startswith('cuda') else 'llvm_ad'
    polarized = '_polarized' if '_polarized' in variant else ''
    close = [f'{backend}_{colour}{polarized}' for colour in ('rgb', 'mono')]
    usable = usable_variants()
    return [v for v in close if v in usable] or usable or close


def variant_problem(variant: str) -> str | None:
    """Why ``variant`` cannot be set here for these plugins — not in this Mitsuba build, not
    supported (:func:`support_problem`), or its backend missing on this machine — or None."""
    if variant not in mi.variants():
        return (f'unknown variant "{variant}"; variants of this Mitsuba build: '
                f'{", ".join(mi.variants())}')
    problem = support_problem(variant)
    if problem:
        return problem
    if not backend_available(variant):
        device = 'no CUDA device (GPU and driver)' if variant.startswith('cuda') else \
            'no usable libLLVM (>= 17)'
        return (f'Dr.Jit finds {device} on this machine; variants that work here: '
                f'{", ".join(usable_variants()) or "none"}')
    return None


def require_supported(plugin: str) -> None:
    problem = support_problem(mi.variant())
    if problem:
        raise UnsupportedVariantError(f'{plugin}: variant {mi.variant()!r}: {problem}')


def rgb_to_spectrum(rgb: mi.Color3f) -> mi.UnpolarizedSpectrum:
    """Linear RGB → the variant's ``UnpolarizedSpectrum`` (RGB as is, mono as luminance)."""
    if mi.is_monochromatic:
        return mi.UnpolarizedSpectrum(mi.luminance(rgb))
    return mi.UnpolarizedSpectrum(rgb)


def backend_available(variant: str) -> bool:
    """Can Dr.Jit run ``variant``'s backend on this machine (a CUDA device for ``cuda_*``, a
    usable libLLVM for ``llvm_*``)? Scalar variants need none."""
    import drjit as dr
    if variant.startswith('cuda'):
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    if variant.startswith('llvm'):
        return bool(dr.has_backend(dr.JitBackend.LLVM))
    return True


def usable_variants() -> list[str]:
    """The variants of this Mitsuba build that the plugins support and this machine can run."""
    return [v for v in mi.variants() if not _unsupported(v) and backend_available(v)]
