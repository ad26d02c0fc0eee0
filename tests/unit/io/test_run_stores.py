"""The array handles of :mod:`mmflow.io.run_stores`: the store builders declare every array through
one, and every handle is an array a builder declares."""
import pickle

import pytest

from mmflow.conventions import m_blocks
from mmflow.io import run_stores as rs
from mmflow.io.run_stores import STORES, ArrayFamily, ArrayName
from mmflow.io.store_docs import LMAX, M_BLOCK, N_FREQ, reference_stores

#: what a family's index runs over in the reference configuration (store_docs)
INDICES = {"fi": range(N_FREQ), "m0": [m0 for m0, _ in m_blocks(LMAX, M_BLOCK)], "m": range(LMAX + 1)}


def _named(family, indices=INDICES):
    """Every array a family names in the reference configuration."""
    names = [()]
    for p in family.params:
        names = [i + (k,) for i in names for k in indices[p]]
    return {family(*i) for i in names}


def test_every_declared_array_is_a_handle_of_its_store_and_every_handle_is_declared():
    """The builders declare their arrays through the handles (the names are written once, in
    :data:`~mmflow.io.run_stores.ARRAYS`). For every store, in the reference configuration with every
    optional array included: each array a builder declares is an :class:`ArrayName` of that store (a
    name written as a string, or another store's handle, fails), and the handles' names (families
    expanded over the reference channels, m blocks and orders) are exactly the declared arrays (a
    handle no builder declares fails); every handle is a ``str`` equal to its name and knows its store."""
    built = [(b(**kw), kw) for b, kw in reference_stores()]
    specs = {spec.path: spec for spec, _ in built}
    # a store with blocks of m of its own (the stokes stage's) names its families by those
    indices = {spec.path: {**INDICES, "m0": [m0 for m0, _ in kw["blocks"]]} if "blocks" in kw else INDICES
               for spec, kw in built}
    assert set(specs) == set(STORES) == set(rs.ARRAYS)
    for store in STORES:
        declared = [a.name for a in specs[store].arrays]
        strays = [n for n in declared if not (isinstance(n, ArrayName) and n.store == store)]
        assert not strays, f"{store}: arrays declared without their handle: {strays}"
        handles = rs.HANDLES[store]
        names = set()
        for attr, h in handles.items():
            assert getattr(store, attr) is h
            names |= _named(h, indices[store]) if isinstance(h, ArrayFamily) else {h}
        for name in names:
            assert isinstance(name, ArrayName) and name.store == store and type(str(name)) is str
        assert names == set(declared), f"{store}: handles no builder declares: {sorted(names - set(declared))}"


def test_a_family_formats_like_the_builder():
    assert STORES.normal.gram(1, 10) == "f1/gram_b00010" and STORES.partials.gram(0, 0) == "f0/gram_b00000"
    assert STORES.partials.rhs(3) == "f3/rhs" and STORES.transfer.B(0, 7) == "f0/B_m00007"
    assert STORES.clean.residual(2, 120).store == STORES.clean
    with pytest.raises(TypeError, match=r"takes \(fi, m0\)"):
        STORES.clean.chol(0)


def test_a_misspelt_array_fails_at_the_call_naming_the_store_s_arrays():
    with pytest.raises(AttributeError, match=r"gains.zarr declares no array 'gain'.*flux_factor, gains, flags"):
        STORES.gains.gain
    assert not hasattr(STORES.vis, "__wrapped__")  # dunder lookups (pickle, copy, inspect) stay plain


def test_handles_survive_pickling():
    """Task functions run in worker processes: a handle arrives as itself, its store included."""
    h = pickle.loads(pickle.dumps(STORES.normal.gram(1, 10)))
    assert isinstance(h, ArrayName) and h == "f1/gram_b00010" and h.store == STORES.normal
    assert pickle.loads(pickle.dumps(STORES.vis)).lst == "lst"


def test_a_declaration_that_would_shadow_a_str_method_or_repeat_is_refused():
    with pytest.raises(ValueError, match="count"):
        rs.store_handles(STORES.vis, ("vis", "count"))
    with pytest.raises(ValueError, match="twice"):
        rs.store_handles(STORES.vis, ("vis", "vis"))
    with pytest.raises(ValueError, match="twice"):
        rs.store_handles(STORES.normal, ("gram", dict(gram="f{fi}/gram_b{m0:05d}")))
