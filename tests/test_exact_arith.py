"""The hub's exactly rounded helpers (agents/admm.py) made faster must give the very same bits.

`_solve_spd` is checked against a straightforward reference -- a fresh matrix per call, the
right-looking Cholesky written out, the triangular solves by math.fsum -- on random, badly
scaled and ill-conditioned systems (and its packed factor against the square one, entry by
entry, for every split of numpy and Python columns), and against exact rational arithmetic for how close it is;
`_pairwise_sum` against math.fsum. Then the paper preset is run twice in process, once with the
reference helper swapped in: every robot's every iterate must be equal to the bit.
"""

from __future__ import annotations

import functools
import math
import operator
import threading
from fractions import Fraction

import numpy as np
import pytest

import agents.admm as admm


def reference_factor(H: np.ndarray) -> np.ndarray:
    """The plain right-looking Cholesky of `reference_solve_spd` on a fresh square matrix: L in
    the lower triangle (the pivots on the diagonal), what `_spd_factor` must give bit for bit."""
    A = np.array(H, dtype=float)
    n = len(A)
    for k in range(n):
        if not A[k, k] > 0:
            raise np.linalg.LinAlgError("not positive definite")
        A[k, k] = lkk = math.sqrt(A[k, k])
        col = A[k + 1 :, k]
        col /= lkk
        A[k + 1 :, k + 1 :] -= np.multiply.outer(col, col)
    return np.tril(A)


def reference_solve_spd(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The plain form of `_solve_spd`: a new matrix, one rank-1 update per column
    (`reference_factor`), fsum solves."""
    A = reference_factor(H)
    n = len(A)
    y = [0.0] * n
    for i in range(n):
        y[i] = (float(g[i]) - math.fsum(A[i, j] * y[j] for j in range(i))) / A[i, i]
    x = [0.0] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - math.fsum(A[j, i] * x[j] for j in range(i + 1, n))) / A[i, i]
    return np.array(x, dtype=float)


def factor_as_matrix(factor: admm.SpdFactor, n: int) -> np.ndarray:
    """`_spd_factor`'s three sequences read back into L, each checked against the others."""
    rows, cols_up, diagonal = factor
    assert len(rows) == n * (n + 1) // 2 and len(cols_up) == n * (n - 1) // 2 and len(diagonal) == n
    L = np.zeros((n, n))
    L[np.tril_indices(n)] = rows  # row after row, the diagonal last in each
    assert list(diagonal) == L.diagonal().tolist()
    assert list(cols_up) == [L[j, i] for i in range(n - 1, -1, -1) for j in range(n - 1, i, -1)]
    return L


def _systems(rng: np.random.Generator, sizes: list[int] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Gram matrices like Anderson's (differences of nearby vectors, + a small ridge), of every
    size up to 40 (or `sizes`), some badly scaled, some nearly singular."""
    out = []
    for n in sizes or [*range(1, 41), 30, 30, 30]:
        dim = int(rng.integers(max(n, 2), 3 * n + 8))
        a = rng.normal(size=(n, dim)) * np.exp(rng.normal(scale=3, size=(n, 1)))  # rows of wildly different size
        kind = len(out) % 3
        if kind == 1 and n > 2:  # nearly dependent rows: condition numbers up to ~1e12
            a[-1] = a[0] + 1e-6 * rng.normal(size=dim) * np.abs(a[0]).max()
        h = np.array([[math.fsum((a[i] * a[j]).tolist()) for j in range(n)] for i in range(n)])
        h[np.diag_indices(n)] += (1e-5 if kind != 2 else 1e-12) * math.fsum(np.diag(h).tolist()) / n
        out.append((h, rng.normal(size=n) * 10.0 ** rng.integers(-6, 6)))
    return out


def test_solve_spd_is_the_reference_bit_for_bit() -> None:
    """Random, badly scaled and ill-conditioned systems of sizes 1..40: the same bits as the
    plain reference, and the input left as it was."""
    rng = np.random.default_rng(2026)
    for H, g in _systems(rng):
        before = H.copy()
        got, want = admm._solve_spd(H, g), reference_solve_spd(H, g)
        assert got.tobytes() == want.tobytes(), len(H)
        assert np.array_equal(H, before)


@pytest.mark.parametrize("tail", [0, 1, 3, 12, 100])
def test_solve_spd_same_bits_wherever_the_scalar_tail_starts(monkeypatch: pytest.MonkeyPatch, tail: int) -> None:
    """`_spd_factor` finishes its last SPD_SCALAR_TAIL columns on Python floats: all numpy (0),
    all Python (100) or any split between must give the reference's bits."""
    monkeypatch.setattr(admm, "SPD_SCALAR_TAIL", tail)
    rng = np.random.default_rng(77)
    for H, g in _systems(rng)[::3]:
        assert admm._solve_spd(H, g).tobytes() == reference_solve_spd(H, g).tobytes(), len(H)


@pytest.mark.parametrize("tail", [0, 1, 2, 3, 6, 12, 100])
def test_packed_factor_is_the_square_right_looking_factor_bit_for_bit(monkeypatch: pytest.MonkeyPatch,
                                                                       tail: int) -> None:
    """`_spd_factor` works on the packed lower triangle (gathered products, the last
    SPD_SCALAR_TAIL columns on Python floats): every entry of L must be the plain square form's,
    bit for bit, for sizes 1..60 (the relay hub's Anderson systems reach 50), Anderson-like,
    badly scaled and nearly singular with a tiny ridge, for every split of numpy and Python
    columns (all numpy: 0, all Python: 100)."""
    monkeypatch.setattr(admm, "SPD_SCALAR_TAIL", tail)
    for H, want in _factored_systems():
        n = len(H)
        assert factor_as_matrix(admm._spd_factor(H), n).tobytes() == want, (n, tail)


@functools.cache
def _factored_systems() -> list[tuple[np.ndarray, bytes]]:
    """Systems of sizes 1..60 with their reference factors' bytes (made once for every split)."""
    return [(H, reference_factor(H).tobytes()) for H, _g in _systems(np.random.default_rng(100), [*range(1, 61)])]


def test_subtract_reduce_over_the_first_axis_is_a_loop_of_subtractions() -> None:
    """`_Hub._extrapolate` relies on np.subtract.reduce(terms, axis=0) being
    ((t0 - t1) - t2) - ... row after row (no pairwise or reordered reduction) on the numpy
    installed: checked against the loop, to the bit, on cancelling rows of several shapes."""
    rng = np.random.default_rng(9)
    for shape in [(2, 1), (3, 7), (24, 64), (31, 5, 9), (7, 33)]:
        t = rng.normal(size=shape) * np.exp(rng.normal(scale=6, size=shape))
        t[1:] += t[:1] * (1 - 1e-12)  # cancellation: any other order of the subtractions shows
        want = t[0].copy()
        for row in t[1:]:
            want = want - row
        assert np.subtract.reduce(t, axis=0).tobytes() == want.tobytes(), shape


def test_solve_spd_close_to_the_exact_rational_solution() -> None:
    """On well-conditioned systems the answer is within a few ulps of the exact one (Fractions):
    a rewrite that kept the bits of a wrong formula would fail here."""
    rng = np.random.default_rng(5)
    for n in (1, 2, 5, 9):
        a = rng.normal(size=(n, n + 3))
        H = a @ a.T + np.eye(n)
        g = rng.normal(size=n)
        M = [[Fraction(float(v)) for v in row] for row in H]
        b = [Fraction(float(v)) for v in g]
        for c in range(n):  # Gauss-Jordan in exact arithmetic
            p = M[c][c]
            M[c] = [v / p for v in M[c]]
            b[c] /= p
            for r in range(n):
                if r != c and M[r][c] != 0:
                    f = M[r][c]
                    M[r] = [vr - f * vc for vr, vc in zip(M[r], M[c])]
                    b[r] -= f * b[c]
        exact = np.array([float(v) for v in b])
        assert np.allclose(admm._solve_spd(H, g), exact, rtol=1e-13, atol=1e-15), n


def test_solve_spd_refuses_what_is_not_positive_definite() -> None:
    """Same refusal as before (LinAlgError; ValueError for a matrix that is not square), and a
    call after a refusal is unaffected by it."""
    H = np.array([[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(np.linalg.LinAlgError):
        admm._solve_spd(H, np.ones(2))
    with pytest.raises(np.linalg.LinAlgError):
        admm._solve_spd(np.array([[float("nan")]]), np.ones(1))
    with pytest.raises(ValueError):  # not square: refused (main's work matrix refused it too), not clipped
        admm._solve_spd(np.ones((3, 4)), np.ones(3))
    ok = np.array([[4.0, 2.0], [2.0, 3.0]])
    assert admm._solve_spd(ok, np.ones(2)).tobytes() == reference_solve_spd(ok, np.ones(2)).tobytes()


def test_solve_spd_in_threads_is_the_reference() -> None:
    """Fleets run in worker threads (launcher/api.py): each thread's work matrix is its own."""
    systems = _systems(np.random.default_rng(11))
    want = [reference_solve_spd(H, g).tobytes() for H, g in systems]
    bad: list[int] = []

    def work() -> None:
        for _ in range(3):
            for i, (H, g) in enumerate(systems):
                if admm._solve_spd(H, g).tobytes() != want[i]:
                    bad.append(i)

    threads = [threading.Thread(target=work) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not bad


def test_pairwise_sum_is_math_fsum_on_random_and_cancelling_sums() -> None:
    """Terms of every count up to 70 (and 127-129), wide-ranging and near-cancelling columns."""
    rng = np.random.default_rng(3)
    for n in [*range(1, 71), 127, 128, 129]:
        q = rng.normal(size=(n, 6)) * np.exp(rng.normal(scale=8, size=(n, 6)))
        q[n // 2 :, 3:] = -q[: n - n // 2, 3:] * (1 + 1e-10 * rng.normal(size=(n - n // 2, 3)))
        got = admm._pairwise_sum(q.copy())
        assert [float(v).hex() for v in got] == [math.fsum(q[:, j].tolist()).hex() for j in range(6)], n


def reference_pairwise_sum(q: np.ndarray) -> np.ndarray:
    """`_pairwise_sum` level by level: each level's sums and their TwoSum errors together."""
    n = len(q)
    if n == 0:
        return np.zeros(q.shape[1:])
    h = 1 << (max(n - 1, 1).bit_length() - 1)
    if n == 2 * h:
        s, e = admm._two_sum(q[:h], q[h:])
    else:
        s, e = q[:h].copy(), np.zeros((h,) + q.shape[1:])
        s[: n - h], e[: n - h] = admm._two_sum(s[: n - h], q[h:])
    while h > 1:
        h //= 2
        s, err = admm._two_sum(s[:h], s[h : 2 * h])
        e = (e[:h] + e[h : 2 * h]) + err
    return s[0] + e[0]


def test_pairwise_sum_is_the_level_by_level_form_bit_for_bit() -> None:
    """`_pairwise_sum` computes the errors of its later levels all at once: the same bits as
    level by level for every count of terms up to 140 (and 256, 300), 1-D and 2-D, wide-ranging,
    cancelling, signed zeros, infinities and NaN."""
    rng = np.random.default_rng(31)
    for n in [*range(0, 141), 256, 300]:
        for shape in [(n,), (n, 1), (n, 5)]:
            q = rng.normal(size=shape) * np.exp(rng.normal(scale=8, size=shape))
            q[n // 2 :] -= q[: n - n // 2] * (1 + 1e-10 * rng.normal(size=(n - n // 2, *shape[1:])))
            if n > 6 and len(shape) == 2 and shape[1] == 5:
                q[:, 0], q[:, 1] = 0.0, -0.0
                q[::3, 1] = 0.0
                q[n // 3, 2], q[n // 2, 3], q[n - 1, 3], q[1, 4] = np.inf, np.inf, -np.inf, np.nan
            with np.errstate(invalid="ignore"):  # (inf - inf: NaN in both forms)
                got, want = admm._pairwise_sum(q), reference_pairwise_sum(q)
            assert got.tobytes() == want.tobytes(), (n, shape)


def test_paper_preset_same_bits_with_the_reference_helper(monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper preset in process (hub + Anderson, 3 robots, to convergence): every iterate of
    every robot equal to the bit with the reference `_solve_spd` swapped in, the exact solve's
    error the same."""
    from launcher.simulate import simulate_fleet
    from launcher.world import Options, build_world

    _world, spec = build_world(Options(preset="paper"))
    fast = simulate_fleet(spec)
    calls = []

    def counted(H: np.ndarray, g: np.ndarray) -> np.ndarray:
        calls.append(len(H))
        return reference_solve_spd(H, g)

    monkeypatch.setattr(admm, "_solve_spd", counted)
    monkeypatch.setattr(admm, "SHARED_STEPS_KEPT", 0)  # every robot computes its own step
    plain = simulate_fleet(spec)
    assert len(calls) > 100 and max(calls) >= 10  # the helper really ran, on systems of some size
    assert [r["rounds"] for r in fast.robots] == [r["rounds"] for r in plain.robots]
    for a, b in zip(fast.robots, plain.robots):
        assert a["trace"].keys() == b["trace"].keys()
        assert all(np.asarray(a["trace"][k]).tobytes() == np.asarray(b["trace"][k]).tobytes() for k in a["trace"])
        assert np.asarray(a["x"]).tobytes() == np.asarray(b["x"]).tobytes() and a["gamma"] == b["gamma"]
