"""Procedural solid textures for the synthetic scene (numpy, float64 in, float32 out).

Textures are functions of the 3D surface point, so a surface point has the same colour in
every view (no texture coordinates, no view dependence). They are band-limited to a few
cells per scene unit so that a ~256 px render does not alias badly, yet carry enough
non-repeating detail for SIFT matching and photometric losses.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ValueNoise", "SolidTexture"]


class ValueNoise:
    """Lattice 3D value noise with C channels, smoothstep-interpolated, values in [0, 1].

    The random lattice is a [L, L, L, C] table (L = 64) addressed modulo L; each octave of
    :meth:`fbm` adds its own random offset, and texture frequencies are not integer ratios
    of each other, so the sum does not visibly repeat within the scene.
    """

    L = 64

    def __init__(self, rng: np.random.Generator, channels: int = 1):
        self.values = rng.random((self.L ** 3, channels)).astype(np.float32)
        self.channels = channels

    def __call__(self, pts: np.ndarray, frequency: float, offset: np.ndarray | None = None) -> np.ndarray:
        """Noise at ``pts`` [N, 3] (scene units) with ``frequency`` cells per unit -> [N, C]."""
        q = np.asarray(pts, np.float64) * frequency
        if offset is not None:
            q = q + offset
        i0 = np.floor(q)
        f = (q - i0).astype(np.float32)
        s = f * f * (3.0 - 2.0 * f)  # smoothstep weights
        i0 = i0.astype(np.int64)
        L, m = self.L, self.L - 1
        ix = [(i0[:, 0] & m) * (L * L), ((i0[:, 0] + 1) & m) * (L * L)]
        iy = [(i0[:, 1] & m) * L, ((i0[:, 1] + 1) & m) * L]
        iz = [i0[:, 2] & m, (i0[:, 2] + 1) & m]
        wx = [1.0 - s[:, 0], s[:, 0]]
        wy = [1.0 - s[:, 1], s[:, 1]]
        wz = [(1.0 - s[:, 2])[:, None], s[:, 2][:, None]]
        out = np.zeros((len(q), self.channels), np.float32)
        for dx in (0, 1):
            for dy in (0, 1):
                base = ix[dx] + iy[dy]
                wxy = wx[dx] * wy[dy]
                inner = self.values[base + iz[0]] * wz[0] + self.values[base + iz[1]] * wz[1]
                out += wxy[:, None] * inner
        return out

    def fbm(self, pts: np.ndarray, base: float, octaves: int, rng_offsets: np.ndarray) -> np.ndarray:
        """Fractal sum of ``octaves`` octaves (frequency doubling, amplitude halving) -> [N, C]
        in [0, 1]; ``rng_offsets`` [octaves, 3] decorrelates the octaves."""
        total = np.zeros((len(pts), self.channels), np.float32)
        norm = 0.0
        for o in range(octaves):
            amp = 0.5 ** o
            total += amp * self(pts, base * 2 ** o, rng_offsets[o])
            norm += amp
        return total / norm


class SolidTexture:
    """The albedo of one object: two-colour fbm mix, colourful blobs, an optional rotated
    checker and fine detail. Parameters are drawn from ``rng`` (deterministic per seed)."""

    def __init__(self, rng: np.random.Generator, noise: ValueNoise, checker: bool, detail_freq: float = 6.0):
        self.noise = noise
        self.palette = rng.random((4, 3)) * 0.85 + 0.1
        self.blob_color = rng.random(3)
        self.blob_color /= max(self.blob_color.max(), 1e-6)
        self.offsets = rng.uniform(0, 256, (4, 3, 3))
        self.base_freq = rng.uniform(0.6, 1.2)
        self.detail_freq = detail_freq
        self.checker = checker
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        self.checker_rot = q
        self.checker_size = rng.uniform(0.18, 0.3)

    def __call__(self, pts: np.ndarray) -> np.ndarray:
        """Albedo [N, 3] float64 in [0, 1] at surface points ``pts`` [N, 3]."""
        n = self.noise
        mix = n.fbm(pts, self.base_freq, 2, self.offsets[0])[:, :1]
        col = self.palette[0] * (1 - mix) + self.palette[1] * mix
        tint = n(pts, self.base_freq * 2.3, self.offsets[1, 0])[:, :3]
        col = col * 0.75 + 0.25 * tint
        blob = n(pts, self.base_freq * 1.5, self.offsets[2, 0])[:, :1]
        b = np.clip((blob - 0.62) / 0.08, 0.0, 1.0)
        col = col * (1 - b) + self.blob_color * b
        if self.checker:
            c = (pts @ self.checker_rot.T) / self.checker_size
            parity = (np.floor(c).astype(np.int64).sum(axis=1) & 1)[:, None]
            col = np.where(parity == 1, col, col * 0.45 + self.palette[2] * 0.25)
        detail = n.fbm(pts, self.detail_freq, 2, self.offsets[3])[:, :1]
        col = col * (0.65 + 0.7 * detail)
        return np.clip(col, 0.0, 1.0)
