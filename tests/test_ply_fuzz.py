"""Fuzzing ``read_ply`` with hypothesis: mutated/truncated valid checkpoints (binary LE, BE,
ASCII; SH degree 0..3; with/without normals and sigma_d) and random headers.

Property: ``read_ply`` either returns a valid ``Gaussians`` (float32, consistent shapes, finite
values) or raises ``PlyFormatError``; never another exception type, never a hang (a hard
per-example time limit via SIGALRM, on top of hypothesis' deadline).

The number of cases is bounded for CI (``CLOD_FUZZ_EXAMPLES`` per test, default 200) and the
generation is derandomised (same cases every run); set ``CLOD_FUZZ_RANDOM=1`` to explore.
"""
from __future__ import annotations

import contextlib
import io
import os
import signal
import tempfile
from pathlib import Path

import numpy as np
import plyfile
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from clod_adapter.io.ply import PlyFormatError, ply_property_names, read_ply

MAX_EXAMPLES = int(os.environ.get("CLOD_FUZZ_EXAMPLES", "200"))
HARD_LIMIT_S = 5.0  # per example: a hang fails the test instead of stalling CI

FUZZ = settings(
    max_examples=MAX_EXAMPLES,
    deadline=2000,  # ms per example
    derandomize=not os.environ.get("CLOD_FUZZ_RANDOM"),
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

FORMATS = ("binary_little_endian", "binary_big_endian", "ascii")
_DIR = Path(tempfile.mkdtemp(prefix="clod_ply_fuzz_"))


class _Hang(Exception):
    pass


@contextlib.contextmanager
def _time_limit(seconds: float):
    def handler(signum, frame):
        raise _Hang(f"read_ply ran longer than {seconds} s")

    old = signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _valid_ply_bytes(n: int, degree: int, normals: bool, sigma_d: bool, fmt: str, seed: int,
                     dtype: str = "f4") -> bytes:
    names = ply_property_names(degree, with_normals=normals, with_sigma_d=sigma_d)
    rng = np.random.default_rng(seed)
    vals = rng.standard_normal((n, len(names))).astype(np.float32)
    order = ">" if fmt == "binary_big_endian" else "<"
    vertex = np.empty(n, dtype=[(nm, order + dtype) for nm in names])
    for i, nm in enumerate(names):
        vertex[nm] = vals[:, i]
    el = plyfile.PlyElement.describe(vertex, "vertex")
    buf = io.BytesIO()
    plyfile.PlyData([el], text=(fmt == "ascii"), byte_order=order).write(buf)
    return buf.getvalue()


def _check(data: bytes, name: str = "f.ply", must_read: bool = False) -> None:
    """Read ``data`` as a .ply: a :class:`PlyFormatError` naming the file (unless ``must_read``:
    then it fails the test) or a consistent, finite float32 model."""
    path = _DIR / name
    path.write_bytes(data)
    try:
        with _time_limit(HARD_LIMIT_S):
            g = read_ply(path)
    except PlyFormatError as e:
        assert not must_read, f"a valid file was refused: {e}"
        assert str(path) in str(e)
        return
    # a model came back: it must be a consistent, finite float32 model
    n = g.means.shape[0]
    assert g.means.shape == (n, 3) and g.quats.shape == (n, 4) and g.log_scales.shape == (n, 3)
    assert g.opacity_logits.shape == (n,) and g.sh0.shape == (n, 1, 3)
    assert g.shN.ndim == 3 and g.shN.shape[0] == n and g.shN.shape[2] == 3
    assert g.shN.shape[1] in (0, 3, 8, 15)
    assert g.sigma_d is None or g.sigma_d.shape == (n,)
    for k, t in g.tensors().items():
        assert t.dtype == torch.float32, k
        assert bool(torch.isfinite(t).all()), k


# --- strategies ---------------------------------------------------------------------------------
valid_files = st.builds(
    _valid_ply_bytes,
    n=st.integers(0, 4),
    degree=st.integers(0, 3),
    normals=st.booleans(),
    sigma_d=st.booleans(),
    fmt=st.sampled_from(FORMATS),
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from(["f4", "f4", "f8", "i2", "u1"]),
)

_mutation = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 1 << 16), st.integers(0, 7)),
    st.tuples(st.just("set"), st.integers(0, 1 << 16), st.integers(0, 255)),
    st.tuples(st.just("truncate"), st.integers(0, 1 << 16), st.just(0)),
    st.tuples(st.just("delete"), st.integers(0, 1 << 16), st.integers(1, 64)),
    st.tuples(st.just("insert"), st.integers(0, 1 << 16), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("header"), st.integers(0, 1 << 16),
              st.sampled_from([b"float", b"double", b"uchar", b"int", b"list uchar float", b"char",
                               b"element vertex 1000000000000", b"element vertex -1",
                               b"element vertex 4294967296", b"element face 2", b"end_header",
                               b"format ascii 1.0", b"format binary_big_endian 1.0",
                               b"format binary_little_endian 2.0", b"property float x",
                               b"property float f_rest_0", b"property list int int x",
                               b"comment \xff\xfe", b"obj_info x", b"", b"\r", b"\x00"])),
)


def _mutate(data: bytes, muts) -> bytes:
    b = bytearray(data)
    for op, pos, arg in muts:
        if not b and op != "insert":
            continue
        pos = pos % (len(b) + 1)
        if op == "flip" and pos < len(b):
            b[pos] ^= 1 << arg
        elif op == "set" and pos < len(b):
            b[pos] = arg
        elif op == "truncate":
            del b[pos:]
        elif op == "delete":
            del b[pos:pos + arg]
        elif op == "insert":
            b[pos:pos] = arg
        elif op == "header":
            # replace one header line (the header ends at end_header)
            end = b.find(b"end_header")
            lines = bytes(b[: end if end >= 0 else len(b)]).split(b"\n")
            i = pos % max(len(lines), 1)
            lines[i] = arg
            b = bytearray(b"\n".join(lines) + (bytes(b[end:]) if end >= 0 else b""))
    return bytes(b)


_TYPES = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8",
          "int16", "uint16", "int32", "uint32", "float32", "float64", "bogus", ""]
_NAMES = ply_property_names(3, with_sigma_d=True) + ["", "x y", "vertex_indices", "é", "0"]


@st.composite
def random_headers(draw) -> bytes:
    fmt = draw(st.sampled_from(list(FORMATS) + ["binary", "ascii2", ""]))
    version = draw(st.sampled_from(["1.0", "1.1", "0", "x"]))
    lines = [b"ply", f"format {fmt} {version}".encode()]
    for _ in range(draw(st.integers(0, 3))):
        name = draw(st.sampled_from(["vertex", "face", "foo", "", "vertex vertex"]))
        count = draw(st.one_of(st.integers(-3, 6), st.sampled_from([2**31, 2**40, 10**18, 2**64]),
                               st.text(max_size=3)))
        lines.append(f"element {name} {count}".encode("utf-8", "surrogatepass"))
        for _ in range(draw(st.integers(0, 14))):
            if draw(st.integers(0, 9)) == 0:
                lines.append(f"property list {draw(st.sampled_from(_TYPES))} "
                             f"{draw(st.sampled_from(_TYPES))} {draw(st.sampled_from(_NAMES))}".encode())
            else:
                lines.append(f"property {draw(st.sampled_from(_TYPES))} "
                             f"{draw(st.sampled_from(_NAMES))}".encode())
            if draw(st.integers(0, 20)) == 0:
                lines.append(draw(st.binary(max_size=12)))
    if draw(st.booleans()):
        lines.append(b"comment " + draw(st.binary(max_size=8)))
    lines.append(b"end_header")
    eol = draw(st.sampled_from([b"\n", b"\r\n"]))
    body = draw(st.one_of(
        st.binary(max_size=256),
        st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), max_size=60).map(
            lambda xs: " ".join(repr(x) for x in xs).encode()),
    ))
    return eol.join(lines) + eol + body


# --- tests --------------------------------------------------------------------------------------
@FUZZ
@given(data=valid_files)
def test_valid_files_read(data):
    """Unmutated generated files are read (integer/double types too)."""
    _check(data, must_read=True)


@FUZZ
@given(data=valid_files, muts=st.lists(_mutation, min_size=1, max_size=4))
def test_mutated_files_never_crash(data, muts):
    _check(_mutate(data, muts))


@FUZZ
@given(data=random_headers())
def test_random_headers_never_crash(data):
    _check(data)


@pytest.mark.parametrize("fmt", FORMATS)
def test_truncation_everywhere_is_a_format_error(fmt):
    """Every proper prefix of a small file either fails with PlyFormatError or (when the cut
    falls in the trailing bytes of an ASCII file) still parses."""
    data = _valid_ply_bytes(3, 1, True, True, fmt, seed=1)
    for cut in range(0, len(data), max(1, len(data) // 150)):
        _check(data[:cut])


@pytest.mark.parametrize("count", ["1000000000000", "4294967296", "9223372036854775807",
                                   "99999999999999999999", "-1"])
@pytest.mark.parametrize("fmt", FORMATS)
def test_absurd_vertex_counts(fmt, count):
    """Header counts far beyond the file size are format errors, not MemoryError/OverflowError."""
    data = _valid_ply_bytes(2, 0, False, False, fmt, seed=2)
    data = data.replace(b"element vertex 2", f"element vertex {count}".encode(), 1)
    _check(data)
