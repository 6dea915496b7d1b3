"""The sliding window of (15a) at a fixed step h with bounded memory.

y(t_k) = int_{t_k - T}^{t_k} g ds by the trapezoidal rule on the samples g_k = g(k h),
with g = 0 before t0 (the convention of docs/conventions.md; "defined behaviour while the
window fills").  Memory: a ring of NB = T / (B h) block sums of B intervals each (nb x m
doubles) instead of T / h samples: B = 10 divides the 4.6 MiB of the paper's arm at
1 kHz by 10.  Inside the oldest block the left edge is interpolated linearly
(y = P + S - (i/B) oldest, exact at block boundaries); the window stays a linear
functional of g, so z = phi^T theta + w carries over to Y = Psi theta + W exactly.

Round-off: a running sum S += new - old would drift.  Each completed block is also added
to a shadow sum; after NB blocks the shadow is exactly the sum of the ring and replaces S,
so S carries at most NB subtractions' round-off, at O(m) cost per block (no spike).
"""
from __future__ import annotations

import numpy as np

__all__ = ["BlockWindow"]


class BlockWindow:
    """Window integral of an m-vector sampled every h over T = NB B h seconds."""

    def __init__(self, m, T, h, block=10):
        m, block = int(m), int(block)
        if m < 1 or block < 1:
            raise ValueError(f"m and block must be >= 1, got m = {m}, block = {block}")
        if not (T > 0 and h > 0):
            raise ValueError(f"T and h must be > 0, got T = {T!r}, h = {h!r}")
        N = round(T / h)
        if abs(N * h - T) > 1e-9 * T or N % block:
            raise ValueError(f"T / h = {T / h:.9g} must be a whole number of samples "
                             f"divisible by block = {block}")
        self.m, self.h, self.B, self.NB = m, float(h), block, N // block
        self.ring = np.zeros((self.NB, m))
        self.pos = 0                      # oldest block
        self.P = np.zeros(m)              # current partial block
        self.i = 0                        # intervals in P
        self.S = np.zeros(m)              # sum of the ring
        self.shadow = np.zeros(m)
        self.nshadow = 0
        self.g_prev = None

    @property
    def nbytes(self):
        return self.ring.nbytes + 5 * self.m * 8

    def push(self, g):
        """Add the sample g_k (the next sample time) and return y(t_k) (a new array)."""
        g = np.asarray(g, dtype=float)
        if self.g_prev is not None:
            self.P += 0.5 * self.h * (self.g_prev + g)
            self.i += 1
            if self.i == self.B:
                old = self.ring[self.pos]
                self.S += self.P - old
                old[:] = self.P
                self.pos = (self.pos + 1) % self.NB
                self.shadow += self.P
                self.nshadow += 1
                if self.nshadow == self.NB:
                    self.S[:] = self.shadow
                    self.shadow[:] = 0.0
                    self.nshadow = 0
                self.P[:] = 0.0
                self.i = 0
        self.g_prev = g.copy()
        return self.P + self.S - (self.i / self.B) * self.ring[self.pos]
