/* Compiled pair kernel of parjam's force evaluation (parjam/kernels.py loads it with ctypes).
 *
 * For the neighbour pairs (i < j, sorted by (i, j)) that touch the owned particles [lo, hi),
 * adds the contact forces to the owned particles in pair order -- so the sum on a particle does
 * not depend on how particles are split over ranks -- and returns the energy of the pairs whose
 * first particle is owned (each pair counted once over all ranks).
 * Positions need not be folded into [0, L) exactly (see the minimum image below).
 * V = (eps/alpha)(1 - r/sigma)^alpha for r < sigma, sigma = (s_i + s_j)/2.
 */
#include <math.h>
#include <stdint.h>

static double powa(double x, double a)
{
    return a == 1.0 ? x : (a == 2.0 ? x * x : pow(x, a));
}

double parjam_pair_forces(int64_t npairs, const int64_t *pi, const int64_t *pj, const double *pos,
                          const double *diam, double L, int d, double alpha, double eps,
                          int64_t lo, int64_t hi, double *force)
{
    double energy = 0.0;
    for (int64_t k = 0; k < (hi - lo) * d; k++)
        force[k] = 0.0;
    for (int64_t p = 0; p < npairs; p++) {
        const int64_t i = pi[p], j = pj[p];
        double dr[3], r2 = 0.0;
        for (int a = 0; a < d; a++) {
            const double xi = pos[i * d + a], xj = pos[j * d + a];
            double x = xj - xi;
            /* minimum image (positions are kept near [0, L), so this loops at most once or twice).
             * Across the boundary x ~ +-L would round at ulp(L); the particle near L is shifted by
             * L first (exact for positions in [L/2, 2L]) and the small numbers are subtracted, so
             * overlaps of 1e-8 keep ~1e-16 absolute precision whatever L (parjam.system). */
            if (x > 0.5 * L) {
                double xs = xj - L;
                while (xs - xi > 0.5 * L)
                    xs -= L;
                x = xs - xi;
            } else if (x < -0.5 * L) {
                double xs = xi - L;
                while (xj - xs < -0.5 * L)
                    xs -= L;
                x = xj - xs;
            }
            dr[a] = x;
            r2 += x * x;
        }
        const double sigma = 0.5 * (diam[i] + diam[j]);
        if (r2 >= sigma * sigma)
            continue;
        const double r = sqrt(r2);
        const double delta = 1.0 - r / sigma;
        const double dv = -(eps / sigma) * powa(delta, alpha - 1.0); /* V'(r) */
        const double c = -dv / r;                                    /* force on j = c dr */
        if (j >= lo && j < hi)
            for (int a = 0; a < d; a++)
                force[(j - lo) * d + a] += c * dr[a];
        if (i >= lo && i < hi) {
            for (int a = 0; a < d; a++)
                force[(i - lo) * d + a] -= c * dr[a];
            energy += (eps / alpha) * powa(delta, alpha);
        }
    }
    return energy;
}
