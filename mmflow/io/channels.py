"""Which file channels an ingest keeps, and their average (``observation.freqs_mhz``, ``input.average_channels``).

Files may hold one spectral setup each or one subband each (different frequency sets, one file per
subband per integration, as the OVRO-LWA correlator writes them): the plan groups the files by
their frequency set, and every output channel comes from one set.

Selection (:func:`select_channels`): each requested frequency ``f`` takes the file channel ``k``
nearest it, refused when ``|nu_k - f|`` exceeds half a channel width (the message names the
nearest channels); with ``N = input.average_channels`` the output is the block of ``N``
consecutive channels of ``k``'s set centred on ``k`` (``k - (N - 1) // 2 .. k + N // 2``, moved
inside the set at its edges). Without requested frequencies every channel is kept, in blocks of
``N`` consecutive channels of each set (a ragged remainder at a set's top is dropped).

Averaging (:func:`average_channels`), as pyuvdata's ``UVData.frequency_average`` (weighted by
``nsample``, flags not propagated): over a block ``B`` with unflagged samples ``U``
(``U = B`` when all are flagged, and the result is then flagged),

    V = sum_U n_c V_c / sum_U n_c,    n = sum_U n_c / |B|,    nu = mean_B nu_c,    width = sum_B width_c.
"""
from __future__ import annotations

import numpy as np

from mmflow.errors import InputError


def frequency_sets(freqs_per_file, rtol=1e-9):
    """Group files by frequency set: ``(sets, set_of_file)`` with ``sets`` a list of frequency arrays
    (Hz) ordered by their lowest frequency and ``set_of_file[i]`` the set of file ``i``."""
    sets, of_file = [], []
    for f in freqs_per_file:
        f = np.asarray(f, float).ravel()
        for k, s in enumerate(sets):
            if s.shape == f.shape and np.allclose(s, f, rtol=rtol, atol=0):
                of_file.append(k)
                break
        else:
            sets.append(f)
            of_file.append(len(sets) - 1)
    order = np.argsort([s.min() for s in sets], kind="stable")
    rank = np.empty(len(sets), int)
    rank[order] = np.arange(len(sets))
    return [sets[k] for k in order], [int(rank[k]) for k in of_file]


def _overlaps(sets, width):
    for a in range(len(sets)):
        for b in range(a + 1, len(sets)):
            close = np.abs(sets[a][:, None] - sets[b][None, :]) < width / 2
            if close.any():
                i, j = np.argwhere(close)[0]
                return a, b, sets[a][i]
    return None


def select_channels(sets, width_hz, want_mhz, n_avg, what="input files", set_files=None):
    """Output channels: a list of ``(set, block)`` (``block``: channel indices into ``sets[set]``).

    Parameters
    ----------
    sets : list of ndarray
        Channel frequencies (Hz) of each frequency set (:func:`frequency_sets`).
    width_hz : float
        A file channel's width.
    want_mhz : list of float or None
        ``observation.freqs_mhz`` (None: every channel).
    n_avg : int
        ``input.average_channels``.
    what : str
        The input, for messages.
    set_files : list of str, optional
        A file holding each set, for messages.
    """
    clash = _overlaps(sets, width_hz)
    if clash is not None:
        a, b, f = clash
        names = set_files or [f"the set starting at {x[0] / 1e6:.6f} MHz" for x in sets]
        raise InputError(names[b], "freq_array", f"its frequencies overlap those of {names[a]} (both hold a "
                         f"channel at {f / 1e6:.6f} MHz) but differ from them",
                         "ingest one spectral setup, or disjoint subbands, per run")
    n_avg = int(n_avg)
    short = [k for k, s in enumerate(sets) if len(s) < n_avg]
    if want_mhz is None:
        if len(short) == len(sets):
            raise InputError(what, "input.average_channels", f"{n_avg} channels to average, but the files hold at "
                             f"most {max(len(s) for s in sets)} per subband", "lower input.average_channels")
        out = [(k, np.arange(b * n_avg, (b + 1) * n_avg)) for k, s in enumerate(sets) for b in range(len(s) // n_avg)]
        return sorted(out, key=lambda kb: sets[kb[0]][kb[1]].mean())
    allf = np.concatenate(sets)
    owner = np.concatenate([np.full(len(s), k) for k, s in enumerate(sets)])
    index = np.concatenate([np.arange(len(s)) for s in sets])
    out = []
    for f_mhz in want_mhz:
        f = float(f_mhz) * 1e6
        near = np.argsort(np.abs(allf - f), kind="stable")
        k = int(near[0])
        if abs(allf[k] - f) > width_hz / 2:
            names = ", ".join(f"{allf[j] / 1e6:.6f}" for j in sorted(near[:2], key=lambda j: allf[j]))
            raise InputError(what, "observation.freqs_mhz", f"{f_mhz:g} MHz is {abs(allf[k] - f) / 1e3:.1f} kHz "
                             f"from the nearest file channel (more than half the {width_hz / 1e3:g} kHz channel "
                             f"width); the nearest channels are at {names} MHz (the files span "
                             f"{allf.min() / 1e6:.6f}-{allf.max() / 1e6:.6f} MHz)",
                             "list frequencies of file channels (or null for every channel)")
        s, c = int(owner[k]), int(index[k])
        n = len(sets[s])
        if n < n_avg:
            raise InputError(what, "input.average_channels", f"{n_avg} channels to average around {f_mhz:g} MHz, "
                             f"but its subband holds {n}", "lower input.average_channels")
        start = min(max(c - (n_avg - 1) // 2, 0), n - n_avg)
        out.append((s, np.arange(start, start + n_avg)))
    return out


def average_channels(vis, flags, nsample, blocks):
    """``(vis, flags, nsample)`` averaged over each block of channels (axis 1; see the module docstring).

    Parameters
    ----------
    vis, flags, nsample : ndarray (nblt, nfreq, npol)
    blocks : list of int arrays (channel indices along axis 1)

    Returns
    -------
    ndarrays (nblt, len(blocks), npol)
    """
    nb = len(blocks)
    if all(len(b) == 1 for b in blocks):  # selection only: exact copies
        idx = np.array([b[0] for b in blocks])
        return vis[:, idx], flags[:, idx], nsample[:, idx]
    out_v = np.zeros((vis.shape[0], nb, vis.shape[2]), np.result_type(vis.dtype, np.complex128))
    out_f = np.zeros(out_v.shape, bool)
    out_n = np.zeros(out_v.shape, np.float64)
    for o, b in enumerate(blocks):
        v, fl, n = vis[:, b], flags[:, b], np.asarray(nsample[:, b], np.float64)
        all_flagged = fl.all(axis=1)
        use = np.where(all_flagged[:, None], True, ~fl)
        w = np.where(use, n, 0.0)
        wsum = w.sum(axis=1)
        num = np.where(use, w * v, 0).sum(axis=1)
        out_v[:, o] = np.where(wsum > 0, num / np.where(wsum > 0, wsum, 1.0), 0)
        out_f[:, o] = all_flagged
        out_n[:, o] = wsum / len(b)
    return out_v.astype(vis.dtype, copy=False), out_f, out_n
