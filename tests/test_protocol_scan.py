"""protocol.scan.check_object_count: the count msgpack would unpack, stopped at the limit."""

from __future__ import annotations

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import ProtocolError
from protocol.scan import check_object_count

# float32-representable floats: packable as float32 and float64 alike
scalars = (st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats(width=32)
           | st.text(max_size=300) | st.binary(max_size=70_000))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=20)
                      | st.dictionaries(st.text(max_size=8), inner, max_size=20), max_leaves=200)


def objects(value) -> int:
    if isinstance(value, dict):
        return 1 + sum(objects(k) + objects(v) for k, v in value.items())
    if isinstance(value, list):
        return 1 + sum(objects(v) for v in value)
    return 1


@settings(max_examples=100, deadline=None)
@given(values, st.booleans())
def test_counts_what_msgpack_unpacks(value, single_float):
    data = msgpack.packb(value, use_bin_type=True, use_single_float=single_float)
    assert check_object_count(data, 10**9) == objects(value)


@settings(max_examples=100, deadline=None)
@given(values, st.integers(1, 50))
def test_refuses_past_the_limit_and_never_fails_otherwise(value, limit):
    data = msgpack.packb(value, use_bin_type=True)
    if objects(value) > limit:
        with pytest.raises(ProtocolError) as err:
            check_object_count(data, limit)
        assert err.value.code == "too_large"
    else:
        assert check_object_count(data, limit) == objects(value)


@given(st.binary(max_size=200))
def test_arbitrary_bytes_end_the_walk_without_error(data):
    count = check_object_count(data, 10**9)  # malformed: the unpacker reports it afterwards
    assert 0 <= count <= max(1, 2 ** 33)


def test_extension_types_and_huge_declared_counts():
    ext = msgpack.packb([msgpack.ExtType(1, b"x" * n) for n in (1, 2, 4, 8, 16, 3, 300, 70000)])
    assert check_object_count(ext, 100) == 9
    declared = b"\xdd\xff\xff\xff\xff" + b"\x01" * 10  # array32 of 2^32 - 1, ten present
    assert check_object_count(declared, 100) == 11
    with pytest.raises(ProtocolError):
        check_object_count(b"\xdd\xff\xff\xff\xff" + b"\x01" * 200, 100)
