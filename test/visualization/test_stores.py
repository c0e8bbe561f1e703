import pytest

from aefabmap_ros.visualization.stores import ByteBoundedStore


def test_the_oldest_go_first_once_over_budget():
    store: ByteBoundedStore[bytes] = ByteBoundedStore(10, len)
    for stamp, value in enumerate([b"aaaa", b"bbb", b"cc", b"dddd"]):
        store.add(stamp, value)
    # 4 + 3 + 2 + 4 = 13 > 10: the first (4 bytes) goes, 9 remain.
    assert 0 not in store and [store.get(s) for s in (1, 2, 3)] == [b"bbb", b"cc", b"dddd"]
    assert store.nbytes == 9 and len(store) == 3


def test_a_value_larger_than_the_budget_is_refused_and_evicts_nothing():
    store: ByteBoundedStore[bytes] = ByteBoundedStore(4, len)
    store.add(1, b"ab")
    assert store.add(2, b"abcde") is False
    assert store.get(1) == b"ab" and store.nbytes == 2


def test_replacing_and_popping_keep_the_byte_count():
    store: ByteBoundedStore[bytes] = ByteBoundedStore(100, len)
    store.add(1, b"abc")
    store.add(1, b"abcdef")
    assert store.nbytes == 6
    assert store.pop(1) == b"abcdef" and store.nbytes == 0 and store.pop(1) is None


def test_budget_must_be_positive():
    with pytest.raises(ValueError):
        ByteBoundedStore(0, len)
