"""Property-based tests of tt's file readers (Hypothesis): random bytes, truncations and
random values in the motion-file, token-file and designs.json readers give a valid result
or tt's own error (`tt.kernels.errors.TTError`), never another exception."""

from __future__ import annotations

import io
import json
import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tt.kernels.errors import TTError

#: Examples per property: modest for the default suite; TT_FUZZ_EXAMPLES=400 for a longer hunt.
FUZZ = settings(
    max_examples=int(os.environ.get("TT_FUZZ_EXAMPLES", 40)),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


def _npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """Valid files of each kind, as bytes."""
    from tt.sim.designs import get_space, save_designs
    from tt.sim.motions import get_motion, save_npz
    from tt.sim.motions.base import Motion
    from tt.tokens.tokenize import tokenize_models

    root = tmp_path_factory.mktemp("good")
    toss = get_motion("toss")
    save_npz(Motion("short", toss.pos[:12], toss.quat[:12], toss.dt), root / "m.npz")
    sp = get_space("viperx")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tokenize_models([sp.model(sp.nominal())]).tokens.save(root / "t.npz")
    save_designs(sp.sample(2, 0), root / "d.json")
    return {k: (root / f).read_bytes() for k, f in (("motion", "m.npz"), ("tokens", "t.npz"), ("designs", "d.json"))}


def _read(kind: str, path):
    if kind == "motion":
        from tt.sim.motions import load_motion_file

        return load_motion_file(path)
    if kind == "tokens":
        from tt.tokens.batch import TokenBatch

        return TokenBatch.load(path)
    from tt.sim.designs import load_designs

    return load_designs(path)


def _check(kind: str, data: bytes, tmp_path) -> None:
    path = tmp_path / ("f.json" if kind == "designs" else "f.npz")
    path.write_bytes(data)
    try:
        _read(kind, path)
    except TTError:
        pass


KINDS = ("motion", "tokens", "designs")


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.binary(max_size=2048))
def test_random_bytes(kind, data, tmp_path):
    _check(kind, data, tmp_path)


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(cut=st.floats(0.0, 1.0), flip=st.integers(0, 1 << 30), byte=st.integers(1, 255))
def test_truncated_or_flipped_files(kind, cut, flip, byte, good, tmp_path):
    data = bytearray(good[kind][: int(len(good[kind]) * cut)])
    _check(kind, bytes(data), tmp_path)
    data = bytearray(good[kind])
    data[flip % len(data)] ^= byte
    _check(kind, bytes(data), tmp_path)


_shapes = st.lists(st.integers(0, 5), min_size=0, max_size=3).map(tuple)
_values = st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, 1e300, 0.5, 0.02])
_dtypes = st.sampled_from(["f8", "f4", "i8", "u1", "bool", "U3", "c16"])


@st.composite
def _array(draw):
    shape, dtype, value = draw(_shapes), draw(_dtypes), draw(_values)
    if dtype == "U3":
        return np.full(shape, "ab", dtype=dtype)
    with np.errstate(invalid="ignore", over="ignore"):  # NaN cast to an integer: whatever it gives
        return np.full(shape, value).astype(dtype)


@FUZZ
@given(fields=st.dictionaries(st.sampled_from(["pos", "quat", "dt", "pos2", "quat2", "name"]), _array(), max_size=6))
def test_motion_file_random_values(fields, tmp_path):
    _check("motion", _npz_bytes(**fields), tmp_path)


@FUZZ
@given(
    replace=st.dictionaries(
        st.sampled_from(
            ["schema_version", "link/values", "link/ids", "link/mask", "geom/values", "geom/mask", "nope/values"]
        ),
        _array(),
        max_size=3,
    ),
    drop=st.lists(st.sampled_from(["schema_version", "link/values", "link/ids", "link/mask"]), max_size=2),
)
def test_token_file_random_values(replace, drop, good, tmp_path):
    arrays = dict(np.load(io.BytesIO(good["tokens"])))
    for k in drop:
        arrays.pop(k, None)
    arrays.update(replace)
    _check("tokens", _npz_bytes(**arrays), tmp_path)


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@FUZZ
@given(value=_json, where=st.integers(0, 1 << 20), index=st.integers(-3, 3) | st.none())
def test_designs_json_random_values(value, where, index, good, tmp_path):
    data = json.loads(good["designs"])
    _check("designs", json.dumps(value).encode(), tmp_path)
    design = data["designs"][where % 2]
    field = ["space", "discrete", "continuous"][where % 3]
    if isinstance(design[field], dict) and design[field] and where % 5:
        design[field][sorted(design[field])[where % len(design[field])]] = value  # one choice replaced
    else:
        design[field] = value
    path = tmp_path / "f.json"
    path.write_text(json.dumps(data))
    from tt.sim.designs import load_designs

    try:
        load_designs(f"{path}#{index}" if index is not None else path)
    except TTError:
        pass
