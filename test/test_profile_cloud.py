"""The profile PointCloud2 layout: round trip, every malformed variant rejected with a reason, and a fuzz
that nothing but ProfileFormatError ever escapes the decoder."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from profile_pose_ros.core.wire.profile_cloud import FLOAT32, Field, ProfileFormatError, decode_profile, encode_profile

FLOAT64 = 8


def layout(points, intensity=None):
    fields, step, data = encode_profile(points, intensity)
    return dict(width=len(points), height=1, fields=fields, is_bigendian=False, point_step=step,
                row_step=step * len(points), data=data)


def sample_points(n=100):
    x = np.linspace(-0.05, 0.05, n)
    points = np.column_stack([x, 0.4 + 0.1 * np.abs(x)])
    points[5] = np.nan
    return points


def test_round_trip_is_float32_exact():
    points = sample_points()
    decoded = decode_profile(**layout(points))
    valid = np.isfinite(points[:, 0])
    assert np.array_equal(decoded[valid], points[valid].astype(np.float32).astype(float))
    assert np.isnan(decoded[5]).all()
    with_intensity = layout(points, intensity=np.ones(len(points)))
    assert with_intensity["point_step"] == 16
    assert [f.name for f in with_intensity["fields"]] == ["x", "y", "z", "intensity"]
    assert np.array_equal(decode_profile(**with_intensity), decoded, equal_nan=True)


def _bad(fragment, **changes):
    args = layout(sample_points())
    args.update(changes)
    with pytest.raises(ProfileFormatError, match=fragment):
        decode_profile(**args)


def test_rejections_say_what_is_wrong():
    points = sample_points()
    _bad("empty cloud", width=0, row_step=0, data=b"")
    _bad("height", height=2)
    _bad("big-endian", is_bigendian=True)
    _bad("row_step", row_step=7)
    _bad("data has", data=layout(points)["data"][:-4])
    _bad("field 'z' is missing", fields=[Field("x", 0, FLOAT32), Field("y", 4, FLOAT32)])
    _bad("field 'x' is FLOAT64", fields=[Field("x", 0, FLOAT64), Field("y", 4, FLOAT32), Field("z", 8, FLOAT32)])
    _bad("does not fit", fields=[Field("x", 0, FLOAT32), Field("z", 10, FLOAT32)])
    _bad("point_step", point_step=0, row_step=0)
    all_nan = np.full((10, 2), np.nan)
    with pytest.raises(ProfileFormatError, match="all 10 points are invalid"):
        decode_profile(**layout(all_nan))
    with pytest.raises(ProfileFormatError, match=r"all 100 points are invalid \(NaN or \+-inf\)"):
        decode_profile(**with_column(2, slice(None), np.inf))  # REP-117's "no return" everywhere
    with pytest.raises(ProfileFormatError, match="y != 0"):
        decode_profile(**with_column(1, slice(None), 0.01))


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("column, value", [(2, np.inf), (2, -np.inf), (0, np.inf)])
def test_rep117_infinities_are_invalid_points_and_the_rest_decode(column, value, compiled):
    """REP-117 codes +inf "no return" and -inf "too close", and some profiler drivers publish them where this
    package's driver publishes NaN: such a point is invalid, like a NaN one, and every other point decodes."""
    points = sample_points()
    decoded = decode_profile(compiled=compiled, **with_column(column, [3, 7], value))
    invalid = np.isnan(decoded).any(axis=1)
    assert invalid[[3, 7]].all() and np.isnan(decoded[[3, 7]]).all()
    assert np.array_equal(invalid, np.isnan(points).any(axis=1) | np.isin(np.arange(len(points)), [3, 7]))
    kept = ~invalid
    assert np.array_equal(decoded[kept], points[kept].astype(np.float32).astype(float))


def with_column(column, rows, value):
    """A valid layout with raw float32 values written into one column (the encoder would sanitise them)."""
    args = layout(sample_points())
    raw = np.frombuffer(args["data"], dtype="<f4").copy().reshape(-1, 3)
    raw[rows, column] = value
    args["data"] = raw.tobytes()
    return args


FIELD = st.builds(Field, st.sampled_from(["x", "y", "z", "intensity", "q"]), st.integers(-4, 40),
                  st.integers(0, 10), st.integers(0, 3))


@settings(max_examples=300, deadline=None)
@given(width=st.integers(-2, 40), height=st.integers(-1, 3), fields=st.lists(FIELD, max_size=5),
       big=st.booleans(), step=st.integers(-4, 40), row=st.integers(-10, 800), data=st.binary(max_size=800))
def test_fuzz_decoder_raises_only_its_own_error(width, height, fields, big, step, row, data):
    try:
        points = decode_profile(width=width, height=height, fields=fields, is_bigendian=big, point_step=step,
                                row_step=row, data=data)
    except ProfileFormatError:
        return
    assert points.shape == (width, 2)
    assert not np.isinf(points).any()


SPECIAL = st.sampled_from([0.0, -0.0, np.nan, np.inf, -np.inf, 1e-3, -0.25, 3.4e38, 1e-45])


@settings(max_examples=300, deadline=None)
@given(rows=st.lists(st.tuples(SPECIAL | st.floats(width=32), SPECIAL | st.floats(width=32),
                               SPECIAL | st.floats(width=32), st.floats(width=32)), min_size=1, max_size=40),
       with_y=st.booleans(), with_intensity=st.booleans())
def test_compiled_decoding_is_the_numpy_reference_bit_for_bit(rows, with_y, with_intensity):
    """One compiled pass (the node's path) against the numpy reference: the same points to the bit (-0.0
    and all), the same invalid (NaN) points, or the same rejection. Which NaN an invalid point holds is
    not compared: for NaN + NaN the CPU returns either operand's, and the compiler may swap them (a
    clean CI run drew x = -NaN, z = NaN: the compiled path gave +NaN, numpy -NaN); nothing reads it."""
    table = np.array(rows, dtype="<f4")[:, : 4 if with_intensity else 3]
    fields = [Field("x", 0, FLOAT32), Field("z", 8, FLOAT32)] + ([Field("y", 4, FLOAT32)] if with_y else [])
    args = dict(width=len(table), height=1, fields=fields, is_bigendian=False, point_step=4 * table.shape[1],
                row_step=4 * table.size, data=table.tobytes())
    outcomes = []
    for compiled in (True, False):
        try:
            points = decode_profile(compiled=compiled, **args)
            outcomes.append((np.isnan(points).tobytes(), np.where(np.isnan(points), 0.0, points).tobytes()))
        except ProfileFormatError as exc:
            outcomes.append(str(exc))
    assert outcomes[0] == outcomes[1]


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0.0, -0.0, 0.01, -0.05, 0.4, np.nan, np.inf, -np.inf]),
                          st.sampled_from([0.3, 0.45, -0.0, np.nan, np.inf])), max_size=40))
def test_encoded_points_are_float32_where_valid_and_nan_in_xyz_where_not(pairs) -> None:
    points = np.array(pairs, dtype=float).reshape(-1, 2)
    _, step, data = encode_profile(points)
    table = np.frombuffer(data, dtype="<f4").reshape(-1, step // 4)
    valid = np.isfinite(points).all(axis=1)
    assert table[valid, 0].tobytes() == points[valid, 0].astype("<f4").tobytes()  # -0.0 stays -0.0
    assert table[valid, 2].tobytes() == points[valid, 1].astype("<f4").tobytes()
    assert np.all(table[valid, 1] == 0) and np.isnan(table[~valid, :3]).all()
