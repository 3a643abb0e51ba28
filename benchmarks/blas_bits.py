"""Which summation order gives the controller's small matrix products bit for bit: what a
compiled controller core would have to reproduce to keep the results unchanged. NumPy
hands these products to its BLAS (OpenBLAS, its kernel chosen at run time for the
processor): the reference's (3, 6) @ (6, 6) samples and the IK's Jᵀ (J Jᵀ)⁻¹ (matrix
products, GEMM), its J Jᵀ (SYRK: NumPy's A @ A.T), its J q and J⁺ e (matrix-vector,
GEMV) and its eᵀ e (DOT). For
each, on this machine, the share of sampled elements that two candidate orders give bit
for bit: a plain left-to-right sum of the products, and the same order with each step a
fused multiply-add (one rounding, as the kernels' FMA instructions do).

    python benchmarks/blas_bits.py [--products 20000]
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from fractions import Fraction

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

# (rows of A, inner dimension, columns of B or None for a vector, B is Aᵀ), what it is
PRODUCTS = (
    ((3, 6, 6, False), "GEMM: the reference's samples (3, 6) @ (6, 6)"),
    ((3, 6, 3, True), "SYRK (A @ A.T): the IK's J Jᵀ (3, 6) @ (6, 3)"),
    ((6, 3, 3, False), "GEMM: the IK's Jᵀ (J Jᵀ)⁻¹ (6, 3) @ (3, 3)"),
    ((3, 6, None, False), "GEMV: the IK's J q (3, 6) @ (6,)"),
    ((6, 3, None, False), "GEMV: the IK's J⁺ e (6, 3) @ (3,)"),
    ((1, 3, None, False), "DOT: the IK's eᵀ e (3,) @ (3,)"),
)


def matching_shares(shape: tuple[int, int, int | None, bool], n: int) -> dict[str, float]:
    """The share of sampled elements of A @ B (random normal) each order gives bit for
    bit: one element of each of ``n`` products."""
    rng = np.random.default_rng(0)
    rows, inner, columns, transposed = shape
    same = dict.fromkeys(ORDERS, 0)
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
    return {name: count / n for name, count in same.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--products", type=int, default=20_000)
    args = parser.parse_args()
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    print(f"NumPy {np.__version__}, BLAS {blas.get('name')} {blas.get('version')}")
    print("| product | " + " | ".join(f"{name}: same bits" for name in ORDERS) + " |")
    print("|---" * (len(ORDERS) + 1) + "|")
    for shape, what in PRODUCTS:
        shares = matching_shares(shape, args.products)
        print(f"| {what} | " + " | ".join(f"{shares[name]:.1%}" for name in ORDERS) + " |")


if __name__ == "__main__":
    main()
