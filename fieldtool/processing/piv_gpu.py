"""Optional GPU backend of the PIV engine (CuPy), selected by ``piv.analyze(backend="auto")`` when usable.

The window spectra, cross-spectra, inverse FFTs and the ensemble sum run on the GPU; the correlation planes come
back to the CPU for the peak search, so the peaks, sub-pixel fit, SNR and validation are exactly the CPU code.
Only single-pass analysis uses the GPU (multi-pass deforms images with OpenCV on the CPU).

Status: UNVERIFIED on real hardware — it was written on a machine without a GPU or CuPy. As a guard, the engine
checks itself once per process on a synthetic pair against the CPU engine and is used only if every displacement
agrees within 0.01 px; otherwise ``available()`` is False and the CPU engine runs.
"""

from __future__ import annotations

import numpy as np

from fieldtool.processing import piv_engine

_CHECKED: bool | None = None


def _cupy():
    try:  # lazy: CuPy is optional (a GPU); its import (CUDA start-up, seconds) only where the GPU engine is tried
        import cupy as cp
        import cupyx.scipy.fft as cfft

        if cp.cuda.runtime.getDeviceCount() < 1:
            return None
        return cp, cfft
    except Exception:  # no CuPy, no driver, no device
        return None


def available() -> bool:
    """True when CuPy with a CUDA device is importable and the GPU engine agrees with the CPU engine."""
    global _CHECKED
    if _CHECKED is None:
        _CHECKED = _cupy() is not None and _self_check()
    return _CHECKED


def _self_check() -> bool:
    rng = np.random.default_rng(0)
    a = rng.random((160, 192)).astype(np.float32)
    b = np.roll(a, (2, -3), (0, 1))
    p = piv_engine.PivParams(window_px=32, overlap_px=16)
    levels, box = piv_engine._levels(a.shape, p, None)
    try:
        cpu = piv_engine._Engine(a.shape, p, levels, box, None)
        gpu = GpuEngine(a.shape, p, levels, box, None)
        dc = cpu.correlate(cpu.prepare(a), cpu.prepare(b))
        dg = gpu.correlate(gpu.prepare(a), gpu.prepare(b))
    except Exception:
        return False
    return bool(np.nanmax(np.abs(dc[0] - dg[0])) < 0.01 and np.nanmax(np.abs(dc[1] - dg[1])) < 0.01)


def usable_for(params) -> bool:
    return params.passes == 1 and params.engine == "fieldtool"


class GpuEngine:
    """Single-pass correlation on the GPU with the CPU engine's geometry and peak code."""

    def __init__(self, shape, params, levels, box, mask):
        self._cpu = piv_engine._Engine(shape, params, levels, box, mask)
        self.cp, self.fft = _cupy()
        self.levels = levels

    def _spectra(self, img, oy, ox, lv, size):
        cp, fft = self.cp, self.fft
        s = lv.s
        st = img.strides
        view = cp.lib.stride_tricks.as_strided(
            img[oy:, ox:], shape=(lv.ny, lv.nx, size, size), strides=(st[0] * lv.step, st[1] * lv.step, st[0], st[1])
        )
        win = cp.ascontiguousarray(view).reshape(lv.ny * lv.nx, size, size)
        win -= win.mean(axis=(1, 2), keepdims=True)
        energy = (win * win).sum(axis=(1, 2))
        inv = cp.where(energy > 1e-6, 1.0 / cp.sqrt(cp.maximum(energy, 1e-12)), 0.0).astype(cp.float32)
        if size != lv.w:  # B window of a search area: energy of a w x w window, as on the CPU
            inv *= np.float32(s / lv.w)
        win *= inv[:, None, None]
        return fft.rfft2(win, s=(s, s), axes=(1, 2))

    def to_device(self, arr: np.ndarray):
        return self.cp.asarray(arr)

    def prepare(self, frame):
        """Crop and mask fill on the CPU (as the CPU engine), window spectra on the GPU."""
        lv0 = self.levels[0]
        f = frame if frame.dtype == np.float32 else frame.astype(np.float32)
        x0, y0, x1, y1 = self._cpu.box
        fill = float(f[y0:y1, x0:x1].mean())
        img = self._cpu._crop(f, fill)
        if self._cpu.mask_crop is not None:
            img = img.copy()
            img[self._cpu.mask_crop] = fill
        g = self.cp.asarray(np.ascontiguousarray(img))
        oy, ox = self._cpu._offsets(lv0)
        spec_a = [self._spectra(g, oy, ox, lv0, lv0.w)]
        spec_b0 = spec_a[0] if lv0.s == lv0.w else self._spectra(g, oy - lv0.margin, ox - lv0.margin, lv0, lv0.s)
        return piv_engine._Frame(img=None, spec_a=spec_a, spec_b0=spec_b0)

    spectrum_only = True  # as the CPU engine: correlate(peaks=False) feeds the ensemble without peaks

    def correlate(self, a, b, cancel=None, ensemble=None, peaks=True):
        """As the CPU engine's ``correlate`` for one pass: total displacement (px) per node and the peaks."""
        lv = self.levels[0]
        cross = self.cp.conj(a.spec_a[0]) * b.spec_b0
        if not peaks:
            ensemble(cross, None, None, None)
            return None, None, None
        corr = self.cp.asnumpy(self.fft.irfft2(cross, s=(lv.s, lv.s), axes=(1, 2)))
        pk = piv_engine._find_peaks(corr, lv.margin)
        if ensemble is not None:
            ensemble(cross, None, None, pk)
        return pk.dx.reshape(lv.ny, lv.nx), pk.dy.reshape(lv.ny, lv.nx), pk

    def ensemble_peaks(self, acc):
        lv = self.levels[0]
        corr = self.cp.asnumpy(self.fft.irfft2(acc, s=(lv.s, lv.s), axes=(1, 2)))
        return piv_engine._find_peaks(corr, lv.margin)
