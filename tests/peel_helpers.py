"""Point-source peeling problems shared by the peeling tests: random arrays, directions and
coherencies of sources (``M_ij = S exp(2 pi i (x_j - x_i).r / lambda)``)."""
import numpy as np

LAM = 7.5  # 40 MHz


def random_array(rng, n):
    x = rng.uniform(-100, 100, (n, 3))
    x[:, 2] *= 0.02
    return x


def point_coherencies(x, dirs, flux, sigma_rad=None):
    """``M_ij = S exp(2 pi i (x_j - x_i).r / lambda)``, optionally a Gaussian of width sigma."""
    b = (x[None, :, :] - x[:, None, :]) / LAM
    m = flux[:, None, None] * np.exp(2j * np.pi * np.einsum("ijk,sk->sij", b, dirs))
    if sigma_rad is not None:
        bperp2 = np.einsum("ijk,ijk->ij", b, b)[None] - np.einsum("ijk,sk->sij", b, dirs) ** 2
        m *= np.exp(-2 * np.pi**2 * np.asarray(sigma_rad)[:, None, None] ** 2 * bperp2)
    return m


def random_directions(rng, n):
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.5
    return d / np.linalg.norm(d, axis=1)[:, None]


def cross_weights(S, N):
    W = np.ones((S, N, N))
    W[:, np.arange(N), np.arange(N)] = 0
    return W
