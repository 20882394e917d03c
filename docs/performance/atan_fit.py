# The coefficients of kAtanSeries in core/angles.cpp (edge_angles' atan2).
# f(z) = atan(sqrt z)/sqrt z = sum (-1)^n z^n/(2n+1) on [0, Z], Z just above
# tan^2(pi/8): the series to degree M, then its highest terms traded one by one
# for shifted Chebyshev polynomials (economisation), in exact rational
# arithmetic. Prints the bound on |economised - f| (the terms traded plus the
# series' tail) and the coefficients rounded to double.
#   python3 docs/performance/atan_fit.py 10
from fractions import Fraction as F
import math, sys
N = int(sys.argv[1]) if len(sys.argv) > 1 else 11
Z = F(1716, 10000)  # above tan^2(pi/8) = 0.171572875...
M = 40
c = [F((-1) ** n, 2 * n + 1) for n in range(M + 1)]
tail = sum(abs(x) * Z ** n for n, x in enumerate(c) if n > M)  # none; truncation bound below
trunc = F(1, 2 * M + 3) * Z ** (M + 1)
def shifted_cheb(n):
    # T_n(2z/Z - 1) as monomial coefficients in z
    a, b = [F(1)], [F(-1), F(2) / Z]
    if n == 0: return a
    for _ in range(n - 1):
        nb = [F(0)] * (len(b) + 1)
        for i, x in enumerate(b):
            nb[i + 1] += 2 * x * F(2) / Z
            nb[i] -= 2 * x
        for i, x in enumerate(a):
            nb[i] -= x
        a, b = b, nb
    return b
added = F(0)
for n in range(M, N, -1):
    t = shifted_cheb(n)
    k = c[n] / t[n]
    for i in range(n + 1):
        c[i] -= k * t[i]
    added += abs(k)  # |T_n| <= 1 on [0, Z]
print("# degree", N, "bound", float(added + trunc))
for i in range(N + 1):
    print(repr(float(c[i])))
