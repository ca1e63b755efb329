"""The twin's noise: a per-leg xorshift64* stream with cheap normal deviates, seeded from
the leg's content (its gains, the experiment), so a point simulated alone or inside a batch
sees the same noise, whatever the threading.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)

# ---------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _next_u64(x):
    """One xorshift64* step of state ``x``: (new state, 64 output bits)."""
    x ^= x >> np.uint64(12)
    x ^= x << np.uint64(25)
    x ^= x >> np.uint64(27)
    return x, x * np.uint64(2685821657736338717)


@njit(cache=True, inline="always")
def _normal(x):
    """(new state, a normal deviate) from one step: the Irwin-Hall sum of four uniforms, the
    output's top 52 bits as four 13-bit integers k_i, u_i = (k_i + 1/2) / 2^13 (mean 1/2 exactly),
    scaled to unit variance; bounded by +-2 sqrt(3), cheap and adequate for noise."""
    x, r = _next_u64(x)
    m = np.uint64(0x1FFF)
    k = (np.int64((r >> np.uint64(12)) & m) + np.int64((r >> np.uint64(25)) & m)
         + np.int64((r >> np.uint64(38)) & m) + np.int64(r >> np.uint64(51)))
    return x, (float(k) + 2.0 - 2.0 * 8192.0) * (1.7320508075688772 / 8192.0)


def _seed_words(seed: int, key) -> list:
    return [int(seed) & 0xFFFFFFFF] + [int(round(float(v) * 1e6)) & 0xFFFFFFFF for v in key]


def seeds_for(seed: int, keys) -> np.ndarray:
    """Per-leg RNG states derived from ``seed`` and each leg's key (content, not order), so
    a point simulated alone or inside a batch sees the same noise.

    Each state is ``np.random.SeedSequence(words).generate_state(1, np.uint64)[0] | 1``
    with ``words`` the seed and the key's values in millionths (rounded half to even),
    each taken modulo 2^32 (about 20 us a leg: under 10 ms for the thesis grid)."""
    out = np.empty(len(keys), dtype=np.uint64)
    for i, key in enumerate(keys):
        out[i] = np.random.SeedSequence(_seed_words(seed, key)).generate_state(1, np.uint64)[0]
    return out | np.uint64(1)
