r"""A sensor's readings at shifted times: what an exact delay between two clocks needs.

A sensor whose samples are late by ``tau`` gives, at the stamp ``t_k``, its signal at
``t_k - tau`` plus its own noise: ``y_k = x(t_k - tau) + n_k``.  What the model predicts at
``t_k`` is ``x(t_k)``, which the readings hold ``tau`` later.  :class:`ShiftedSignal` gives the
readings at ``t_k + tau``, band-limited (a Fourier series of the whole recording), split in two:

- the *bands above the noise* (the series' power averaged over 1 Hz bands, tested against the
  noise's at the level :data:`BAND_ALPHA`; the noise's level measured on the readings,
  :func:`noise_sigma`) are shifted everywhere;
- the *rest* -- the noise, and content below it at its frequency -- is shifted only within
  :data:`TRANSIENT_REACH` of a transient (its mean square over 20 ms above the noise's, or a
  contact's switch given as an event: an impact's content is broadband, weak in each band, strong
  in time), and elsewhere left at its sample.

Why split.  Shifting the whole series is exact, and a shift keeps white noise white with its
variance (it is unitary), but the noise it moves decorrelates from the noise the fit had absorbed
within a sample: the evidence for ``tau`` then varies from sample to sample like a scan over
``tau`` (measured: a clean 3 s TALOS CoM step gave an offset 2 Delta E = 12.2, a wrong
selection; two in the 68 recordings of the wide benchmark).  Moving only part of the noise at
every frequency would lower its variance (an interpolation's average of neighbouring samples, a
Wiener filter's partial gain), and a fit would prefer any shift (measured: 300 in cost on that
sway).  Moving whole bands, or none, keeps the noise's variance at every ``tau``, and the bands
above the noise carry nearly all of what a delay changes; near a transient the whole series
moves, so a touch-down seen ``tau`` late is moved whole (on TALOS's simulated walk, 15 ms:
14.86 +- 0.05 ms; without the transients 14.3).

The derivative on ``tau`` (the effect's Jacobian) is the rate of the readings' *signal*: each
band above the noise weighted by its power above the noise (a Wiener gain), not of the readings
(the derivative of sampled white noise has a standard deviation of ``1.8 sigma / dt``, more than
a slow motion's rate: the information it gives a delay is noise).

The series is made periodic for the Fourier transform by a smooth return from its last sample to
its first over :data:`PAD_S` seconds (a raised cosine), so the ends do not ring; beyond its ends
the readings are that return (close to the end value for a shift of a few samples).
"""

from __future__ import annotations

import math

import numpy as np

from flexforce.errors import DataError

PAD_S = 0.5
"""Seconds of the smooth return appended to the series (at least 64 samples)."""
BAND_HZ = 1.0
"""Width of the bands over which the series' power is averaged (Hz), at least :data:`BAND_MIN` bins."""
BAND_MIN = 5
BAND_ALPHA = 1e-3
"""A band is signal where its averaged power exceeds the noise's at this level (a chi-square test
on ``2 x bins`` degrees of freedom); elsewhere the gain is zero."""
DIRECT_MAX = 64
"""Up to this many times, the signal is summed directly at each; beyond, by inverse FFTs."""
TAYLOR_SPREAD = 1e-5
"""Shifts within this many seconds of their median share its inverse FFTs, with a third-order
Taylor step from the median (its error ``|d|^4 |x^(4)| / 24`` is below 1e-10 of the signal's
amplitude at 100 Hz; a constant effect's per-step values differ by a few microseconds)."""


def noise_sigma(y: np.ndarray) -> np.ndarray:
    """Per-column white-noise sigma of a sampled series, robustly: the median absolute deviation
    of its third differences (``sqrt(20) sigma`` for white noise; a smooth signal's are small --
    ``(omega dt)^3`` of it, 0.045 at 11 Hz and 200 Hz -- and the median ignores the few large ones
    of impacts)."""
    y = np.asarray(y, dtype=float)
    if len(y) < 8:
        return np.zeros(y.shape[1:])
    d3 = y[3:] - 3.0 * y[2:-1] + 3.0 * y[1:-2] - y[:-3]
    mad = np.median(np.abs(d3 - np.median(d3, axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(20.0)


TRANSIENT_S = 0.02
"""Window (s, at least 3 samples) over which the readings' part outside their bands above the
noise is tested for a transient: its mean square against the noise's, at the level
:data:`TRANSIENT_ALPHA` over the series' windows."""
TRANSIENT_ALPHA = 0.01
TRANSIENT_REACH = 0.06
"""Seconds on each side of a transient over which that part is shifted too: beyond the largest
plausible delay (50 ms) and the window."""


def transients(rest: np.ndarray, sigma: np.ndarray, dt: float, events=()) -> np.ndarray:
    """(N, m) 1.0 within :data:`TRANSIENT_REACH` of a transient of ``rest`` (the readings outside
    their bands above the noise: white noise of ``sigma`` where nothing happens, an impact's
    broadband content where one does) or of one of the samples ``events`` (known switches: a
    contact's touch-down or lift-off), else 0.0."""
    from scipy.ndimage import maximum_filter1d, uniform_filter1d
    from scipy.stats import chi2

    n = len(rest)
    L = max(3, int(round(TRANSIENT_S / dt)))
    level = TRANSIENT_ALPHA * L / max(n, L)  # Bonferroni over the series' windows
    with np.errstate(divide="ignore", invalid="ignore"):
        z2 = np.where(sigma > 0, (rest / np.where(sigma > 0, sigma, 1.0)) ** 2, 0.0)
    hit = uniform_filter1d(z2, size=L, axis=0, mode="nearest") > chi2.isf(level, L) / L
    ev = np.asarray(events, dtype=int).reshape(-1)
    hit[ev[(ev >= 0) & (ev < n)]] = True
    reach = 2 * int(np.ceil(TRANSIENT_REACH / dt)) + L
    return maximum_filter1d(hit.astype(float), size=reach, axis=0, mode="nearest")


def _fill(y: np.ndarray, use: np.ndarray | None) -> np.ndarray:
    """Unused entries replaced, per column, by the linear interpolation of the used ones."""
    y = np.array(y, dtype=float)
    if use is None:
        return y
    use = np.asarray(use, dtype=bool)
    idx = np.arange(len(y))
    for j in range(y.shape[1]):
        ok = use[:, j]
        if ok.all():
            continue
        y[~ok, j] = np.interp(idx[~ok], idx[ok], y[ok, j]) if ok.any() else 0.0
    return y


class ShiftedSignal:
    """The readings' signal (module documentation) of a uniformly sampled series.

    Args:
        y: (N, m) readings, one column per axis.
        dt: sampling period, s.
        use: (N, m) True where a reading is valid (others are bridged linearly); default all.
        events: samples known to be transients (a contact's switch), beside those found.
    """

    def __init__(self, y: np.ndarray, dt: float, use: np.ndarray | None = None, events=()):
        y = np.asarray(y, dtype=float)
        if y.ndim != 2 or len(y) < 2:
            raise DataError(f"a delay needs a series of at least 2 samples (rows) per axis; got shape {y.shape}")
        if not dt > 0:
            raise DataError(f"a delay needs a positive sampling period; got {dt}")
        from scipy.fft import irfft, next_fast_len, rfft
        from scipy.ndimage import uniform_filter1d
        from scipy.stats import chi2

        y = _fill(y, use)
        if not np.all(np.isfinite(y)):
            raise DataError("a delay needs finite readings where they are used; the series has NaN or inf")
        self.n, self.m, self.dt = len(y), y.shape[1], float(dt)
        pad = max(64, int(math.ceil(PAD_S / dt)))
        M = next_fast_len(self.n + pad, real=True)
        M += M % 2  # even: the last bin is the Nyquist one, shifted as a cosine (whole samples exactly)
        self.M = M
        u = (np.arange(1, M - self.n + 1) / (M - self.n + 1))[:, None]
        ret = y[-1] + (y[0] - y[-1]) * 0.5 * (1.0 - np.cos(np.pi * u))
        c = rfft(np.concatenate([y, ret]), axis=0)
        self.sigma = noise_sigma(y)
        width = max(BAND_MIN, int(round(BAND_HZ * M * dt))) | 1     # bins averaged: BAND_HZ, odd
        power = uniform_filter1d(np.abs(c) ** 2, size=width, axis=0, mode="nearest")
        floor = M * self.sigma**2
        seen = power > chi2.ppf(1.0 - BAND_ALPHA, 2 * width) / (2 * width) * floor
        with np.errstate(divide="ignore", invalid="ignore"):
            wiener = np.where(power > 0, np.clip(1.0 - floor / np.where(power > 0, power, 1.0), 0.0, 1.0), 0.0)
        gain = np.where(seen, wiener, 0.0)
        wiener[0] = gain[0] = 1.0
        self.gain = gain
        # the readings' bands above their noise, shifted everywhere; the rest (noise, and content
        # below it at its frequency) shifted only near transients, elsewhere left at its sample
        band = np.where(seen, 1.0, 0.0)
        band[0] = 1.0
        self.coef_seen = c * band
        self.coef_rest = c * (1.0 - band)
        self.coef_signal = c * gain
        self.omega = 2.0 * np.pi * np.arange(M // 2 + 1) / (M * dt)
        self.rest = irfft(self.coef_rest, M, axis=0)[: self.n]
        self.transient = transients(self.rest, self.sigma, dt, events)
        self._ffts: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _series(self, tau: float):
        """At every sample shifted by ``tau``: the readings and their first three derivatives, and
        the signal's first three, by inverse FFTs (the last few shifts kept)."""
        got = self._ffts.get(tau)
        if got is None:
            from scipy.fft import irfft

            iw = (1j * self.omega)[:, None]
            ph = np.exp(1j * self.omega * tau)[:, None]
            m = self.transient
            seen = [irfft(self.coef_seen * ph * iw**p, self.M, axis=0)[: self.n] for p in range(4)]
            rest = [irfft(self.coef_rest * ph * iw**p, self.M, axis=0)[: self.n] for p in range(4)]
            sig = [irfft(self.coef_signal * ph * iw**p, self.M, axis=0)[: self.n] for p in range(1, 4)]
            got = (seen[0] + m * rest[0] + (1.0 - m) * self.rest, *(a + m * b for a, b in zip(seen[1:], rest[1:])),
                   *sig)
            if len(self._ffts) >= 4:
                self._ffts.pop(next(iter(self._ffts)))
            self._ffts[tau] = got
        return got

    def _direct(self, k: np.ndarray, tau: np.ndarray):
        """The readings at ``t_k + tau`` and the signal's rate there, summed directly (few times)."""
        w = np.full(len(self.omega), 2.0 / self.M)
        w[[0, -1]] = 1.0 / self.M  # the mean and the Nyquist bin (its cosine: the FFT's reading)
        ph = np.exp(1j * np.outer(k * self.dt + tau, self.omega)) * w      # (n, J)
        m = self.transient[k]
        x = (ph @ self.coef_seen).real + m * (ph @ self.coef_rest).real + (1.0 - m) * self.rest[k]
        xd = (ph @ (self.coef_signal * (1j * self.omega)[:, None])).real
        return x, xd

    def at(self, k, tau) -> tuple[np.ndarray, np.ndarray]:
        """The readings at the times ``t_k + tau_k`` (band-limited; at whole samples, the samples)
        and the rate of their signal there: (n, m) each.

        ``k`` (n,) sample indices, ``tau`` (n,) or scalar shifts in seconds."""
        k = np.asarray(k, dtype=int).reshape(-1)
        tau = np.broadcast_to(np.asarray(tau, dtype=float), k.shape)
        if len(k) <= DIRECT_MAX:
            return self._direct(k, tau)
        x = np.empty((len(k), self.m))
        xd = np.empty((len(k), self.m))
        todo = np.ones(len(k), dtype=bool)
        while todo.any():
            mid = float(np.median(tau[todo]))
            near = todo & (np.abs(tau - mid) <= TAYLOR_SPREAD)
            if not near.any():  # pragma: no cover - the median is within the spread of itself
                near = todo & (tau == tau[todo][0])
                mid = float(tau[todo][0])
            y0, y1, y2, y3, s1, s2, s3 = self._series(mid)
            d = (tau[near] - mid)[:, None]
            kk = k[near]
            x[near] = y0[kk] + d * (y1[kk] + d / 2.0 * (y2[kk] + d / 3.0 * y3[kk]))
            xd[near] = s1[kk] + d * (s2[kk] + d / 2.0 * s3[kk])
            todo &= ~near
        return x, xd

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_ffts"] = {}
        return state
