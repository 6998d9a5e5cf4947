"""Bit-exact round trips of the point word and the shared encodings (numerical stability)."""
import numpy as np
import pytest

from psao.protocol import gridformat as gf
from psao.protocol import pointword as pw


def test_pack_unpack_every_field_bit_exact():
    rng = np.random.default_rng(1)
    q = rng.integers(0, 32, size=(10000, 3)).astype(np.uint32)
    n = rng.integers(0, 256, size=10000).astype(np.uint32)
    ao = rng.integers(0, 256, size=10000).astype(np.uint32)
    words = pw.pack_point(q, n, ao)
    alloc, q2, n2, ao2 = pw.unpack_point(words)
    assert alloc.all()
    np.testing.assert_array_equal(q2, q)
    np.testing.assert_array_equal(n2, n)
    np.testing.assert_array_equal(ao2, ao)
    np.testing.assert_array_equal(pw.pack_point(q2, n2, ao2), words)


def test_field_positions_match_design_table():
    w = int(pw.pack_point(np.array([[1, 2, 3]]), np.array([0xAB]), np.array([0xCD]))[0])
    assert w >> 31 == 1
    assert (w >> 16) & 31 == 1 and (w >> 21) & 31 == 2 and (w >> 26) & 31 == 3
    assert (w >> 8) & 0xFF == 0xAB and w & 0xFF == 0xCD
    assert w == 0x8C41ABCD


def test_six_axis_normals_round_trip_exactly():
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)
    np.testing.assert_array_equal(pw.oct_decode(pw.oct_encode(axes)), axes)


def oct_encode_reference(normals):
    """The octahedral code as written out in DESIGN.md: divide by the L1 norm, fold the lower hemisphere."""
    n = np.asarray(normals, dtype=np.float64)
    l1 = np.abs(n).sum(axis=-1, keepdims=True)
    p = n / np.where(l1 > 0, l1, 1.0)
    u, v, z = p[..., 0], p[..., 1], p[..., 2]
    su, sv = np.where(u >= 0, 1.0, -1.0), np.where(v >= 0, 1.0, -1.0)
    fu = np.where(z < 0, (1.0 - np.abs(v)) * su, u)
    fv = np.where(z < 0, (1.0 - np.abs(u)) * sv, v)
    h = pw.OCT_LEVELS_HALF
    qu = np.clip(np.rint(fu * h) + h, 0, 2 * h).astype(np.uint32)
    qv = np.clip(np.rint(fv * h) + h, 0, 2 * h).astype(np.uint32)
    return (qu << 4) | qv


def test_oct_encode_equals_reference_also_on_signed_zeros():
    rng = np.random.default_rng(4)
    n = rng.normal(size=(200_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    signed = np.array([[s0 * a, s1 * b, s2 * c] for s0 in (1.0, -1.0) for s1 in (1.0, -1.0) for s2 in (1.0, -1.0)
                       for a, b, c in ((0.0, 0.0, 1.0), (0.0, 0.6, 0.8), (0.6, 0.0, 0.8), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))])
    for normals in (n, n.astype(np.float32), signed, signed[3]):
        np.testing.assert_array_equal(pw.oct_encode(normals), oct_encode_reference(normals))


def test_random_normals_within_quantisation_bound():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(2_000_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = pw.oct_decode(pw.oct_encode(n))
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
    angle = np.degrees(np.arccos(np.clip((d * n).sum(axis=1), -1, 1)))
    # 15 levels over [-1, 1] (step 1/7 in octahedral space): the worst case, near the octahedron edges,
    # is 17.1 degrees (the README's figure); the eq. 3 normal test (cos > 0.1, 84 degrees) is far coarser.
    assert 17.05 <= angle.max() < 17.15
    assert np.median(angle) < 7.0
    assert (pw.oct_encode(n) & 0xF).max() <= 14 and (pw.oct_encode(n) >> 4).max() <= 14


def test_points_exactly_on_cell_faces_stay_in_their_cell():
    frac = np.array([[0.0, 0.0, 0.0], [1.0 - 1e-12, 0.5, 0.999999], [1.0, 1.0, 1.0], [-1e-9, 0.0, 0.0]])
    q = pw.quantise_cell_fraction(frac)
    assert q.min() >= 0 and q.max() <= 31
    np.testing.assert_array_equal(q[0], [0, 0, 0])
    np.testing.assert_array_equal(q[2], [31, 31, 31])
    f = pw.dequantise_cell_fraction(q)
    assert (f > 0).all() and (f < 1).all()


def test_position_quantisation_error_bound():
    rng = np.random.default_rng(3)
    frac = rng.random((100000, 3))
    err = np.abs(pw.dequantise_cell_fraction(pw.quantise_cell_fraction(frac)) - frac)
    assert err.max() <= 0.5 / 32 + 1e-6


def test_ao_codes():
    assert pw.quantise_ao(np.array([0.0, 1.0, 0.5, np.nan, 2.0, -1.0])).tolist() == [0, 255, 128, 255, 255, 0]
    codes = np.arange(256, dtype=np.uint32)
    np.testing.assert_array_equal(pw.quantise_ao(pw.dequantise_ao(codes)), codes)


def test_with_ao_keeps_other_bits():
    w = pw.pack_point(np.array([[5, 6, 7]]), np.array([0x3C]), np.array([9]))
    w2 = pw.with_ao(w, np.array([200]))
    assert int(w2[0]) & 0xFFFFFF00 == int(w[0]) & 0xFFFFFF00 and int(w2[0]) & 0xFF == 200


@pytest.mark.parametrize("dims", [(1, 1, 1), (37, 5, 900), (1024, 1024, 1024)])
def test_hash_wraps_like_uint32(dims):
    rng = np.random.default_rng(4)
    c = rng.integers(0, np.array(dims), size=(1000, 3))
    h = gf.cell_hash(c[:, 0], c[:, 1], c[:, 2], dims)
    expect = [(int(x) + int(y) * dims[0] * 17 + int(z) * dims[0] * dims[1] * 31) % 2**32 for x, y, z in c]
    assert h.tolist() == expect
    keys = gf.cell_key(c[:, 0], c[:, 1], c[:, 2], dims)
    np.testing.assert_array_equal(gf.key_to_cell(keys, dims), c)
    assert (keys != gf.EMPTY).all()


def test_instance_record_is_std430_sized():
    assert gf.INSTANCE_DTYPE.itemsize == 48
    assert gf.INSTANCE_DTYPE.fields["dims"][1] == 16 and gf.INSTANCE_DTYPE.fields["bucket_offset"][1] == 28
