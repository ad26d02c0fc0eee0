"""Task keys (issue 23): one format, one parse, and the strings earlier versions named markers by.

The expected strings are written out literally: completion markers of existing run
directories are named by them, so a change here would make old runs unresumable.
"""
import pytest

from mmflow.workflow.engine.chunking import TIME_CHUNK, chunk_rows, time_keys
from mmflow.workflow.engine.task_key import TaskKey

LEGACY = [  # (key, the string earlier versions wrote), one per kind of task
    (TaskKey(time=3), "t00003"),  # simulate, ingest
    (TaskKey(bl_chunk=12), "b00012"),  # mmodes
    (TaskKey(freq=1), "f1"),  # products
    (TaskKey(freq=1, time=3), "f1_t00003"),  # peel
    (TaskKey(freq=0, source=2), "f0_s2"),  # models
    (TaskKey(freq=2, group=7), "f2-g0007"),  # transfer
    (TaskKey(freq=0, m_block=32), "f0-m00032"),  # normal, solve, clean set-up
    (TaskKey(freq=0, m_block=8, cycle=2), "c0002-f0-m00008"),  # clean cycle
    (TaskKey(freq=3, phase="r"), "r3"),  # calibrate ripple
    (TaskKey(freq=1, interval=4, phase="g"), "g1_00004"),  # calibrate gains
    (TaskKey(time=5, phase="s"), "s_t00005"),  # terrestrial sums
    (TaskKey(time=5, phase="a", cycle=0), "c0000-a_t00005"),  # terrestrial amplitudes (second phase)
    (TaskKey(freq=10, m_block=123456), "f10-m123456"),  # wider than the padding: as Python's 05d writes it
]


@pytest.mark.parametrize("key, legacy", LEGACY, ids=[s for _, s in LEGACY])
def test_format_is_the_legacy_string_and_parse_inverts_it(key, legacy):
    assert key.format() == legacy == str(key)
    assert TaskKey.parse(legacy) == key
    assert TaskKey.parse(key.format()) == key


def test_every_layout_round_trips_with_and_without_a_cycle():
    from mmflow.workflow.engine.task_key import LAYOUTS

    values = dict(freq=4, time=11, bl_chunk=2, group=9, m_block=64, source=1, interval=300, phase="s")
    for names in LAYOUTS:
        for cycle in (None, 0, 17):
            k = TaskKey(cycle=cycle, **{n: values[n] for n in names})
            assert TaskKey.parse(k.format()) == k
    assert len({TaskKey(**{n: values[n] for n in names}).format() for names in LAYOUTS}) == len(LAYOUTS)


@pytest.mark.parametrize("text", ["", "t3", "t000003", "f01", "f0-m0032", "f0-m00032-", "f0_t00003x", "c1-f0",
                                  "c0001_f0", "x", "f0_g0001", "F0", "f_t00001", "t00001_s_t00001", "f-1"])
def test_parse_refuses_a_malformed_key(text):
    with pytest.raises(ValueError, match="malformed task key"):
        TaskKey.parse(text)


def test_parse_refuses_what_is_not_a_string():
    with pytest.raises(ValueError, match="malformed task key"):
        TaskKey.parse(3)


@pytest.mark.parametrize("fields, match", [
    (dict(), "no task key has the fields"),
    (dict(freq=0, group=1, m_block=0), "no task key has the fields"),
    (dict(freq=-1), "non-negative integer"),
    (dict(freq=1.0), "non-negative integer"),
    (dict(freq=True), "non-negative integer"),
    (dict(freq=0, phase="f"), "phase"),  # would read back as channel f0
    (dict(time=0, phase="ab"), "phase"),
])
def test_a_key_without_a_layout_or_with_bad_values_is_refused(fields, match):
    with pytest.raises(ValueError, match=match):
        TaskKey(**fields)


def test_time_keys_cover_the_integrations_once():
    n = 2 * TIME_CHUNK + 5
    keys = time_keys(n)
    assert [k.format() for k in keys] == ["t00000", "t00001", "t00002"]
    assert [k.format() for k in time_keys(n, freq=1)] == ["f1_t00000", "f1_t00001", "f1_t00002"]
    rows = [chunk_rows(k, n) for k in keys]
    assert rows == [(0, TIME_CHUNK), (TIME_CHUNK, 2 * TIME_CHUNK), (2 * TIME_CHUNK, n)]
