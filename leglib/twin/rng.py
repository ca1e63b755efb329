"""The twin's noise: a per-leg xorshift64* stream with cheap normal deviates, seeded from
the leg's content (its gains, the experiment), so a point simulated alone or inside a batch
sees the same noise, whatever the threading.
"""

from __future__ import annotations

import numpy as np
from numba import njit

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
    with ``words`` the seed and the key's values in millionths, each taken modulo 2^32.
    It is computed here for all legs at once: the same mixing as numpy's SeedSequence
    (bit_generator.pyx: four pool words, hashmix and mix over uint32, two output words),
    checked against it in tests/test_twin.py. Keys of unequal lengths or huge values go
    through SeedSequence leg by leg."""
    n = len(keys)
    lens = {len(k) for k in keys}
    vals = np.asarray(keys, dtype=float).reshape(n, -1) if len(lens) == 1 else None
    if vals is None or not np.all(np.abs(vals) < 2.0 ** 52 / 1e6):
        out = np.empty(n, dtype=np.uint64)
        for i, key in enumerate(keys):
            out[i] = np.random.SeedSequence(_seed_words(seed, key)).generate_state(1, np.uint64)[0] | np.uint64(1)
        return out
    # Python's round() is numpy's (half to even); |value| < 2^52: exact in int64
    words = [np.full(n, int(seed) & 0xFFFFFFFF, dtype=np.uint32)]
    words += [(np.round(vals[:, j] * 1e6).astype(np.int64) & 0xFFFFFFFF).astype(np.uint32)
              for j in range(vals.shape[1])]
    return _seed_sequence_state(words) | np.uint64(1)
_M32 = 0xFFFFFFFF


def _seed_sequence_state(entropy) -> np.ndarray:
    """``SeedSequence(words).generate_state(1, np.uint64)`` for ``entropy``, a list of
    uint32 arrays over the legs (word k of every leg's words), pool size 4. The hash
    constants do not depend on the data, so they run as Python integers; the data as
    uint32 arrays, which wrap as C does."""
    hc = [0x43B0D7E5]

    def hashmix(value):
        value = value ^ np.uint32(hc[0])
        hc[0] = (hc[0] * 0x931E8875) & _M32
        value = value * np.uint32(hc[0])
        return value ^ (value >> np.uint32(16))

    def mix(x, y):
        r = np.uint32(0xCA01F9DD) * x - np.uint32(0x4973F715) * y
        return r ^ (r >> np.uint32(16))

    with np.errstate(over="ignore"):
        zero = np.zeros_like(entropy[0])
        pool = [hashmix(entropy[i] if i < len(entropy) else zero) for i in range(4)]
        for src in range(4):
            for dst in range(4):
                if src != dst:
                    pool[dst] = mix(pool[dst], hashmix(pool[src]))
        for src in range(4, len(entropy)):
            for dst in range(4):
                pool[dst] = mix(pool[dst], hashmix(entropy[src]))
        hb = 0x8B51F9DD
        state = []
        for i in range(2):
            v = pool[i] ^ np.uint32(hb)
            hb = (hb * 0x58F38DED) & _M32
            v = v * np.uint32(hb)
            state.append(v ^ (v >> np.uint32(16)))
    return state[0].astype(np.uint64) | (state[1].astype(np.uint64) << np.uint64(32))
