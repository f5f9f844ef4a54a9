"""Time per step vs number of landmarks for every registered estimator; prints fitted log-log exponents.

Runs ``slam2d.lab.experiments.scaling`` (grid scenario, one lap per N) and compares the slopes with the lesson's
claims. Same as ``slam2d experiment scaling``; pass N values as arguments, e.g. ``python benchmarks/bench_scaling.py
100 400 1600``.
"""

from __future__ import annotations

import argparse

from slam2d.lab.experiments import scaling


def _count(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"a landmark count must be >= 1 (got {n})")
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("landmarks", nargs="*", type=_count, metavar="N",
                    help="landmark counts, one lap of the grid scenario each (default 100 400 1600 6400)")
    ns = tuple(ap.parse_args().landmarks) or (100, 400, 1600, 6400)
    res = scaling(landmarks=ns, report=print)
    print(f"\n{'estimator':<16} {'slope(mapped)':>13} {'end slope':>10} {'slope(N)':>9}  claim")
    for name, f in res["fits"].items():
        print(f"{name:<16} {f['slope_vs_mapped']:>13.2f} {f['end_slope_vs_mapped']:>10.2f} "
              f"{f['slope_vs_landmarks']:>9.2f}  {f['claim']}")


if __name__ == "__main__":
    main()
