"""PIV through OpenPIV, the reference engine of ``piv.engine = openpiv``: the same pairs, grid and outputs.

One pass: ``pyprocess.extended_search_area_piv``'s correlation planes and peaks; several: ``windef.simple_multipass``
(OpenPIV's window deformation and its own validation). Displacements in px, image axes (as ``piv_engine``).
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
from openpiv import pyprocess, windef
from openpiv.settings import PIVSettings

from fieldtool.errors import ParameterError
from fieldtool.processing.piv_engine import _Engine, _Frame, _Level, _Peaks


class _OpenPivEngine(_Engine):
    """Same pairs, grid and outputs through OpenPIV: ``pyprocess.extended_search_area_piv`` for one pass,
    ``windef.simple_multipass`` (OpenPIV's window deformation and its own validation) for several."""

    def __init__(self, shape, params, levels, box, mask):
        super().__init__(shape, params, levels, box, mask)
        if params.averaging == "ensemble" and len(levels) > 1:
            raise ParameterError(
                "piv.averaging: ensemble is not available with piv.engine = openpiv and piv.passes > 1; "
                "use mean or median, or piv.engine = fieldtool"
            )

    #: no cross-spectrum without peaks here: ``analyze`` correlates every pair (its ensemble sample needs the
    #: CPU engine's ``correlate(peaks=False)``)
    spectrum_only = False

    def prepare(self, frame: np.ndarray, as_a: bool = True, as_b: bool = True) -> _Frame:
        """The masked crop alone (OpenPIV correlates images); ``as_a``/``as_b`` change nothing here."""
        return _Frame(img=self._masked_crop(frame), spec_a=[], spec_b0=None)

    def _sub(self, img: np.ndarray, lv: _Level, size: int) -> np.ndarray:
        """Part of the crop whose OpenPIV grid (windows of ``size`` from 0, step lv.step) is our level grid."""
        oy, ox = self._offsets(lv)
        m = (size - lv.w) // 2
        return img[oy - m : oy - m + lv.step * (lv.ny - 1) + size, ox - m : ox - m + lv.step * (lv.nx - 1) + size]

    def correlate(self, a: _Frame, b: _Frame, cancel=None, ensemble=None, peaks: bool = True):
        """As the CPU engine's, through OpenPIV; the peaks are always found (``peaks`` is accepted, not used)."""
        assert a.img is not None and b.img is not None  # prepare keeps the crop
        lv = self.levels[-1]
        n = lv.ny * lv.nx
        if len(self.levels) == 1:
            fa, fb = self._sub(a.img, lv, lv.s), self._sub(b.img, lv, lv.s)
            corr = self._planes(fa, fb, lv)
            u, v = pyprocess.correlation_to_displacement(corr, lv.ny, lv.nx, subpixel_method="gaussian")
            snr = pyprocess.sig2noise_ratio(corr, sig2noise_method="peak2peak", width=2).ravel()
            peak = corr.reshape(n, -1).max(axis=1)
            if ensemble is not None:
                ensemble(
                    corr,
                    None,
                    None,
                    None
                    if snr is None
                    else _Peaks(dx=u.ravel(), dy=v.ravel(), peak=peak, snr=snr, p2m=snr, ok=np.isfinite(snr)),
                )
        else:
            st = PIVSettings()
            st.windowsizes = tuple(L.w for L in self.levels)
            st.overlap = tuple(L.w - L.step for L in self.levels)
            st.num_iterations = len(self.levels)
            with contextlib.redirect_stdout(io.StringIO()):
                fa, fb = self._sub(a.img, lv, lv.w), self._sub(b.img, lv, lv.w)
                _, _, u, v, flags = windef.simple_multipass(fa, fb, st)
            v = -v  # simple_multipass negates v (tools.transform_coordinates; rows stay in image order)
            snr = np.where(np.asarray(flags).ravel() > 0, 0.0, np.nan)
            peak = np.full(n, np.nan)
        dx, dy = (
            np.asarray(u, dtype=np.float64).reshape(lv.ny, lv.nx),
            np.asarray(v, dtype=np.float64).reshape(lv.ny, lv.nx),
        )
        ok = np.isfinite(dx.ravel()) & np.isfinite(dy.ravel()) & (np.nan_to_num(snr, nan=np.inf) > 0)
        return dx, dy, _Peaks(dx=dx.ravel(), dy=dy.ravel(), peak=peak, snr=snr, p2m=np.full(n, np.nan), ok=ok)

    @staticmethod
    def _planes(fa: np.ndarray, fb: np.ndarray, lv: _Level) -> np.ndarray:
        """OpenPIV's correlation planes, as in extended_search_area_piv (circular FFT, fft-shifted)."""
        aa = pyprocess.sliding_window_array(fa, (lv.s, lv.s), (lv.s - lv.step, lv.s - lv.step))
        bb = pyprocess.sliding_window_array(fb, (lv.s, lv.s), (lv.s - lv.step, lv.s - lv.step))
        if lv.s > lv.w:
            aa = pyprocess.normalize_intensity(aa)
            bb = pyprocess.normalize_intensity(bb)
            m = np.zeros((lv.s, lv.s), dtype=aa.dtype)
            m[lv.margin : lv.margin + lv.w, lv.margin : lv.margin + lv.w] = 1
            aa = aa * m
        return pyprocess.fft_correlate_images(aa, bb, correlation_method="circular", normalized_correlation=False)

    def ensemble_peaks(self, acc: np.ndarray) -> _Peaks:
        lv = self.levels[-1]
        u, v = pyprocess.correlation_to_displacement(acc, lv.ny, lv.nx, subpixel_method="gaussian")
        snr = pyprocess.sig2noise_ratio(acc, sig2noise_method="peak2peak", width=2).ravel()
        ok = np.isfinite(u.ravel()) & np.isfinite(v.ravel())
        return _Peaks(
            dx=u.ravel(),
            dy=v.ravel(),
            peak=acc.reshape(len(snr), -1).max(axis=1),
            snr=snr,
            p2m=np.full(len(snr), np.nan),
            ok=ok,
        )
