"""Why a compiled controller core cannot give the same results bit for bit: the controller's
small matrix products (the reference's (3, 6) @ (6, 6) samples, the IK's 3x6 products) go
through NumPy's BLAS, whose kernel (chosen at run time for the processor) need not sum in
the order a plain loop does. This counts, on this machine, the products whose elements
differ in any bit from a sequential sum of the same terms.

    python benchmarks/blas_bits.py [--products 20000]
"""

from __future__ import annotations

import argparse

import numpy as np


def differing_share(shape_a: tuple[int, int], shape_b: tuple[int, int], n: int) -> float:
    """The share of sampled elements of A @ B (random normal) that a left-to-right sum of
    the products a_ik b_kj does not give bit for bit."""
    rng = np.random.default_rng(0)
    differ = 0
    for _ in range(n):
        a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
        i, j = int(rng.integers(shape_a[0])), int(rng.integers(shape_b[1]))
        total = 0.0
        for k in range(shape_a[1]):
            total += float(a[i, k]) * float(b[k, j])
        differ += total != float((a @ b)[i, j])
    return differ / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--products", type=int, default=20_000)
    args = parser.parse_args()
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    print(f"NumPy {np.__version__}, BLAS {blas.get('name')} {blas.get('version')}")
    for shape_a, shape_b, use in (((3, 6), (6, 6), "the reference's samples"),
                                  ((3, 6), (6, 3), "the IK's J J^T"),
                                  ((6, 3), (3, 3), "the IK's J^T (J J^T)^-1")):  # fmt: skip
        share = differing_share(shape_a, shape_b, args.products)
        print(
            f"{shape_a} @ {shape_b} ({use}): {share:.1%} of elements differ from a sequential sum"
        )


if __name__ == "__main__":
    main()
