"""Exact references for the Riccati tests: Newton's method in rational arithmetic (fractions).

The floats of a problem are exact rationals; from a float start each Newton step (Hewer's for
the DARE, Kleinman's for the CARE) solves its Stein / Lyapunov equation exactly as an n^2 x n^2
linear system, and the iterates are rounded to denominators below 10^120 between steps, so a
few steps give the solution of the stated floats to far beyond float64 precision.
"""

from fractions import Fraction

import numpy as np


def _rational(a):
    return [[Fraction(float(v)) for v in row] for row in np.atleast_2d(a)]


def _mul(a, b):
    return [
        [sum(x * y for x, y in zip(row, col, strict=True)) for col in zip(*b, strict=True)]
        for row in a
    ]


def _t(a):
    return [list(col) for col in zip(*a, strict=True)]


def _lin(*terms):
    """sum of coefficient * matrix."""
    coeff, first = terms[0]
    out = [[coeff * v for v in row] for row in first]
    for coeff, mat in terms[1:]:
        out = [
            [o + coeff * v for o, v in zip(ro, rm, strict=True)]
            for ro, rm in zip(out, mat, strict=True)
        ]
    return out


def _solve(a, b):
    """a x = b by Gauss-Jordan elimination in exact arithmetic."""
    n = len(a)
    rows = [list(a[i]) + list(b[i]) for i in range(n)]
    for c in range(n):
        pivot = next(r for r in range(c, n) if rows[r][c] != 0)
        rows[c], rows[pivot] = rows[pivot], rows[c]
        for r in range(n):
            if r != c and rows[r][c] != 0:
                f = rows[r][c] / rows[c][c]
                rows[r] = [x - f * y for x, y in zip(rows[r], rows[c], strict=True)]
    return [[rows[i][j] / rows[i][i] for j in range(n, len(rows[0]))] for i in range(n)]


def _solve_operator(op, C):
    """N with op(N) = C for a linear map op on n x n matrices (vectorised, exact)."""
    n = len(C)
    basis = [
        [[Fraction(int(i * n + k == j)) for k in range(n)] for i in range(n)] for j in range(n * n)
    ]
    columns = [[v for row in op(E) for v in row] for E in basis]
    system = [[columns[j][i] for j in range(n * n)] for i in range(n * n)]
    solution = _solve(system, [[v] for row in C for v in row])
    return [[solution[i * n + k][0] for k in range(n)] for i in range(n)]


def _round(X):
    n = len(X)
    sym = [[(X[i][j] + X[j][i]) / 2 for j in range(n)] for i in range(n)]
    return [[v.limit_denominator(10**120) for v in row] for row in sym]


def _as_float(X):
    return np.array([[float(v) for v in row] for row in X])


def exact_dare(A, B, Q, R, start, steps=4):
    """Stabilising X of X = A^T X A - A^T X B (R + B^T X B)^-1 B^T X A + Q (the floats given,
    exactly), refined from ``start``; returns (X as floats, largest residual entry)."""
    A, B, Q, R, X = (_rational(v) for v in (A, B, Q, R, start))

    def residual(X):
        BtXA = _mul(_mul(_t(B), X), A)
        K = _solve(_lin((1, R), (1, _mul(_mul(_t(B), X), B))), BtXA)
        At = _t(A)
        return _lin((1, Q), (1, _mul(_mul(At, X), A)), (-1, X), (-1, _mul(_t(BtXA), K))), K

    for _ in range(steps):
        res, K = residual(X)
        Ac = _lin((1, A), (-1, _mul(B, K)))
        N = _solve_operator(
            lambda E: _lin((1, _mul(_mul(_t(Ac), E), Ac)), (-1, E)), _lin((-1, res))
        )
        X = _round(_lin((1, X), (1, N)))
    return _as_float(X), float(max(abs(v) for row in residual(X)[0] for v in row))


def exact_care(A, B, Q, R, start, steps=4):
    """Stabilising X of A^T X + X A - X B R^-1 B^T X + Q = 0 (the floats given, exactly),
    refined from ``start``; returns (X as floats, largest residual entry)."""
    A, B, Q, R, X = (_rational(v) for v in (A, B, Q, R, start))

    def residual(X):
        K = _solve(R, _mul(_t(B), X))
        XA = _mul(X, A)
        return _lin((1, Q), (1, XA), (1, _t(XA)), (-1, _mul(_mul(X, B), K))), K

    for _ in range(steps):
        res, K = residual(X)
        Ac = _lin((1, A), (-1, _mul(B, K)))
        N = _solve_operator(lambda E: _lin((1, _mul(_t(Ac), E)), (1, _mul(E, Ac))), _lin((-1, res)))
        X = _round(_lin((1, X), (1, N)))
    return _as_float(X), float(max(abs(v) for row in residual(X)[0] for v in row))
