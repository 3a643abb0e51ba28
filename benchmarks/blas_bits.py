"""Which summation order gives the controller's small matrix products bit for bit: what a
compiled controller core would have to reproduce to keep the results unchanged. NumPy
hands these products to its BLAS (OpenBLAS, its kernel chosen at run time for the
processor): the reference's (3, 6) @ (6, 6) samples and the IK's Jᵀ (J Jᵀ)⁻¹ (matrix
products, GEMM), its J Jᵀ (SYRK: NumPy's A @ A.T), its J q and J⁺ e (matrix-vector,
GEMV) and its eᵀ e (DOT). For
each, on this machine, the share of sampled elements that two candidate orders give bit
for bit: a plain left-to-right sum of the products, and the same order with each step a
fused multiply-add (one rounding, as the kernels' FMA instructions do); and the whole
product through the routine NumPy calls, called directly (ctypes) from NumPy's bundled
OpenBLAS, as a compiled core would call it.

    python benchmarks/blas_bits.py [--products 20000]
"""

from __future__ import annotations

import argparse
import ctypes
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import numpy as np

Order = Callable[[list[float], list[float]], float]


def fused_multiply_add(a: float, b: float, c: float) -> float:
    """a b + c rounded once (``math.fma`` arrived in Python 3.13): exact rational
    arithmetic, then one correctly rounded conversion."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def plain_sum(a: list[float], b: list[float]) -> float:
    total = 0.0
    for x, y in zip(a, b, strict=True):
        total += x * y
    return total


def fused_sum(a: list[float], b: list[float]) -> float:
    total = 0.0
    for x, y in zip(a, b, strict=True):
        total = fused_multiply_add(x, y, total)
    return total


ORDERS: dict[str, Order] = {"plain sum": plain_sum, "fused multiply-add": fused_sum}
DIRECT = "NumPy's BLAS called directly"

ROW_MAJOR, NO_TRANSPOSE, UPPER = 101, 111, 121  # CBLAS's enumerations


class BundledBlas:
    """The CBLAS routines of NumPy's bundled OpenBLAS (the wheels' scipy-openblas, 64-bit
    integers): the ones NumPy's matmul calls for these products."""

    def __init__(self, library: Path) -> None:
        blas = ctypes.CDLL(str(library))
        i, d, p = ctypes.c_int64, ctypes.c_double, ctypes.POINTER(ctypes.c_double)
        e = ctypes.c_int
        self._gemm = blas.scipy_cblas_dgemm64_
        self._gemm.argtypes = [e, e, e, i, i, i, d, p, i, p, i, d, p, i]
        self._syrk = blas.scipy_cblas_dsyrk64_
        self._syrk.argtypes = [e, e, e, i, i, d, p, i, d, p, i]
        self._gemv = blas.scipy_cblas_dgemv64_
        self._gemv.argtypes = [e, e, i, i, d, p, i, p, i, d, p, i]
        self._dot = blas.scipy_cblas_ddot64_
        self._dot.argtypes = [i, p, i, p, i]
        self._dot.restype = d

    @classmethod
    def found(cls) -> BundledBlas | None:
        libraries = sorted((Path(np.__file__).parent.parent / "numpy.libs").glob("*openblas64_*"))
        return cls(libraries[0]) if libraries else None

    def product(self, a: np.ndarray, b: np.ndarray, transposed: bool) -> np.ndarray:
        """A @ B as a 2-D array (a vector's product as one row)."""
        p = ctypes.POINTER(ctypes.c_double)
        a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
        if a.ndim == 1:
            return np.array([[self._dot(a.size, a.ctypes.data_as(p), 1, b.ctypes.data_as(p), 1)]])
        rows, inner = a.shape
        if b.ndim == 1:
            y = np.zeros(rows)
            self._gemv(ROW_MAJOR, NO_TRANSPOSE, rows, inner, 1.0, a.ctypes.data_as(p), inner,
                       b.ctypes.data_as(p), 1, 0.0, y.ctypes.data_as(p), 1)  # fmt: skip
            return y[:, None]
        if transposed:  # NumPy's A @ A.T: one triangle, mirrored
            c = np.zeros((rows, rows))
            self._syrk(ROW_MAJOR, UPPER, NO_TRANSPOSE, rows, inner, 1.0, a.ctypes.data_as(p),
                       inner, 0.0, c.ctypes.data_as(p), rows)  # fmt: skip
            return np.triu(c) + np.triu(c, 1).T
        columns = b.shape[1]
        c = np.zeros((rows, columns))
        self._gemm(ROW_MAJOR, NO_TRANSPOSE, NO_TRANSPOSE, rows, columns, inner, 1.0,
                   a.ctypes.data_as(p), inner, b.ctypes.data_as(p), columns, 0.0,
                   c.ctypes.data_as(p), columns)  # fmt: skip
        return c


# (rows of A, inner dimension, columns of B or None for a vector, B is Aᵀ), what it is
PRODUCTS = (
    ((3, 6, 6, False), "GEMM: the reference's samples (3, 6) @ (6, 6)"),
    ((3, 6, 3, True), "SYRK (A @ A.T): the IK's J Jᵀ (3, 6) @ (6, 3)"),
    ((6, 3, 3, False), "GEMM: the IK's Jᵀ (J Jᵀ)⁻¹ (6, 3) @ (3, 3)"),
    ((3, 6, None, False), "GEMV: the IK's J q (3, 6) @ (6,)"),
    ((6, 3, None, False), "GEMV: the IK's J⁺ e (6, 3) @ (3,)"),
    ((1, 3, None, False), "DOT: the IK's eᵀ e (3,) @ (3,)"),
)


def matching_shares(
    shape: tuple[int, int, int | None, bool], n: int, blas: BundledBlas | None
) -> dict[str, float]:
    """The share of sampled elements of A @ B (random normal) each order gives bit for
    bit: one element of each of ``n`` products."""
    rng = np.random.default_rng(0)
    rows, inner, columns, transposed = shape
    same = dict.fromkeys([*ORDERS, DIRECT], 0)
    for _ in range(n):
        a = rng.normal(size=(rows, inner)) if rows > 1 else rng.normal(size=inner)
        b = rng.normal(size=(inner, columns)) if columns else rng.normal(size=inner)
        b = a.T if transposed else b
        product = np.atleast_2d(np.asarray(a @ b).reshape(rows, -1))
        i = int(rng.integers(rows))
        j = int(rng.integers(columns)) if columns else 0
        row = np.atleast_2d(a)[i].tolist()
        column = (b[:, j] if columns else b).tolist()
        for name, order in ORDERS.items():
            same[name] += order(row, column) == float(product[i, j])
        if blas is not None:
            same[DIRECT] += float(blas.product(a, b, transposed)[i, j]) == float(product[i, j])
    return {name: count / n for name, count in same.items() if blas is not None or name != DIRECT}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--products", type=int, default=20_000)
    args = parser.parse_args()
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    print(f"NumPy {np.__version__}, BLAS {blas.get('name')} {blas.get('version')}")
    bundled = BundledBlas.found()
    if bundled is None:
        print("(no bundled OpenBLAS found beside NumPy: its column is left out)")
    columns = [*ORDERS, *([DIRECT] if bundled else [])]
    print("| product | " + " | ".join(f"{name}: same bits" for name in columns) + " |")
    print("|---" * (len(columns) + 1) + "|")
    for shape, what in PRODUCTS:
        shares = matching_shares(shape, args.products, bundled)
        print(f"| {what} | " + " | ".join(f"{shares[name]:.1%}" for name in columns) + " |")


if __name__ == "__main__":
    main()
