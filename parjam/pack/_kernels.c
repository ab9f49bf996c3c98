/* Compiled kernels of parjam's force evaluation and FIRE step (parjam/pack/kernels.py loads them with
 * ctypes; scripts/setup-env and `pip install` build them, see kernels.py).
 *
 * parjam_pair_forces: for the neighbour pairs (i < j, sorted by (i, j)) that touch the owned
 * particles [lo, hi), adds the contact forces to the owned particles in pair order -- so the sum
 * on a particle does not depend on how particles are split over ranks -- and returns the energy
 * of the pairs whose first particle is owned (each pair counted once over all ranks).
 * Positions need not be folded into [0, L) exactly (see the minimum image below).
 * V = (eps/alpha)(1 - r/sigma)^alpha for r < sigma, sigma = (s_i + s_j)/2 (the paper's Eq. (1)).
 *
 * parjam_fire_step: one FIRE step fused with the force evaluation (parjam/pack/fire.py): the
 * velocity/position update of the owned particles, the forces at the new positions, and the
 * partial sums that the next step's decisions need (energy, F.v, |F|^2, |v|^2, max |F_i|^2,
 * max |v_i|^2, max displacement^2 since the neighbour list was built), which the caller reduces
 * over the ranks in one allreduce.  The sums are exact (parjam_exact_*: integer accumulators,
 * rounded once at the end), so they, and with them FIRE's trajectory, are the same bits on any
 * number of ranks.
 *
 * parjam_cell_pairs / parjam_slab_pairs: the neighbour searches by cells (whole periodic box;
 * one rank's slab and its ghosts) that list the pairs in the global (i, j) order the sums above
 * rely on.
 *
 * Over 500 lines on purpose: one source is one library with one SHA (kernels.py builds and
 * checks exactly that); splitting it would mean several libraries to build, hash and load.
 */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__SSE2__) && (defined(__x86_64__) || defined(__i386__))
#include <xmmintrin.h>
#endif

#if defined(__GNUC__)
#define ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define ALWAYS_INLINE inline
#endif


/* ---- Exact sums (parjam.net.exactsum): a fixed-point accumulator of every finite double ----
 *
 * A double is m 2^(E - 1074) with an integer mantissa m < 2^53 and E = max(biased exponent, 1)
 * - 1 in 0..2045.  The accumulator holds the exact sum as int64 chunks of 32 bits, chunk k
 * weighing 2^(32 k - 1074) (XACC_CHUNKS of them, the last one signed and open-ended), and
 * counts of NaN, +inf and -inf.  Adding a value adds its two 32-bit-aligned pieces to two
 * chunks (no branch on the sign); the chunks have room for XACC_SLACK additions before the
 * carries must be propagated (``xacc_norm``: every chunk but the last into [0, 2^32)).  Once
 * normalised the representation is unique, so the sum of the ranks' accumulators is an integer
 * sum (MPI_SUM on int64: exact, in any order) and its rounding to a double
 * (``parjam_exact_value``, to nearest, ties to even: math.fsum's value) is the same whatever
 * the split of the values over ranks and their order.  This is the small superaccumulator of
 * R. M. Neal, "Fast exact summation using small and large superaccumulators", arXiv:1505.05571.
 */
#define XACC_CHUNKS 66
#define XACC_NAN 66
#define XACC_PINF 67
#define XACC_MINF 68
#define XACC_LEN 69
#define XACC_SLACK 2000

static ALWAYS_INLINE void xacc_add(int64_t *acc, double x)
{
    uint64_t b;
    memcpy(&b, &x, sizeof b);
    const int e = (int)((b >> 52) & 0x7ff);
    uint64_t m = b & 0xfffffffffffffULL;
    if (e == 0x7ff) {
        acc[m ? XACC_NAN : ((b >> 63) ? XACC_MINF : XACC_PINF)] += 1;
        return;
    }
    int E = 0;
    if (e) {
        m |= 1ULL << 52;
        E = e - 1;
    }
    const int idx = E >> 5, s = E & 31;
    const int64_t low = (int64_t)((m << s) & 0xffffffffULL);
    const int64_t high = (int64_t)(m >> (32 - s));
    const int64_t neg = -(int64_t)(b >> 63); /* 0, or -1 for a negative value */
    acc[idx] += (low ^ neg) - neg;
    acc[idx + 1] += (high ^ neg) - neg;
}

/* Carries propagated: chunks 0 .. XACC_CHUNKS - 2 into [0, 2^32), the last one signed. */
static void xacc_norm(int64_t *acc)
{
    for (int k = 0; k < XACC_CHUNKS - 1; k++) {
        const int64_t c = acc[k] >> 32; /* floor(acc[k] / 2^32) (arithmetic shift) */
        acc[k] &= 0xffffffffLL;
        acc[k + 1] += c;
    }
}

/* ---- Blocks of values added to an accumulator exactly, a few flops per value ----
 *
 * xacc_add costs ~4.5 ns a value on this machine, ~20 % of a FIRE step that makes four exact
 * sums per particle.  A block of at most XBLOCK values whose largest magnitude m is below
 * 2^(E+1) is split instead on two grids, g1 = 2^(E+1-XW) and g2 = g1 2^-XW (Demmel and Nguyen's
 * extraction, as in ReproBLAS): q1 = (x + 1.5 g1 2^52) - 1.5 g1 2^52 is x rounded to a multiple
 * of g1, r = x - q1 is exact, q2 likewise from r on g2, and the remainder x - q1 - q2 is exact.
 * Each grid's values are at most 2^XW of its units, so XBLOCK of them add up in a double without
 * rounding (2^(XW + 8) <= 2^53), and the two block sums go to the accumulator as two values.
 * What the grids do not hold -- the bits of values more than 2^37 below m -- goes to xacc_add
 * value by value, as does a block with a NaN, an infinity, or m outside [2^-900, 2^900].  Every
 * step is exact, so the accumulator receives the same sum as from xacc_add alone (and the result
 * is the same bits): only the time differs.  The grids need IEEE double arithmetic without
 * flush-to-zero: xblock_fast() says so, else blocks take the value-by-value path. */
#define XBLOCK 256
#define XW 45

static int xblock_fast(void)
{
#if FLT_EVAL_METHOD != 0
    return 0; /* excess precision (x87) breaks the rounding on a grid */
#elif defined(__SSE2__) && (defined(__x86_64__) || defined(__i386__))
    return (_mm_getcsr() & 0x8040) == 0; /* neither flush-to-zero nor denormals-are-zero */
#elif defined(__aarch64__) && defined(__GNUC__)
    uint64_t fpcr;
    __asm__ volatile("mrs %0, fpcr" : "=r"(fpcr));
    return (fpcr & (1ULL << 24)) == 0; /* FZ */
#else
    return 1;
#endif
}

static double pow2i(int G) /* 2^G for G in [-1022, 1023] */
{
    const uint64_t b = (uint64_t)(G + 1023) << 52;
    double x;
    memcpy(&x, &b, sizeof x);
    return x;
}

/* Adds x[0..n) (n <= XBLOCK, largest magnitude m unless there is a NaN) to acc exactly; returns
 * the number of xacc_add calls made. */
static int64_t xacc_block(int64_t *acc, const double *x, int n, double m, int fast)
{
    if (m < 0.0) { /* not known: the largest |x| (a NaN is not seen here either) */
        double m4[4] = {0.0, 0.0, 0.0, 0.0};
        int k = 0;
        for (; k + 4 <= n; k += 4)
            for (int l = 0; l < 4; l++) {
                const double a = fabs(x[k + l]);
                m4[l] = a > m4[l] ? a : m4[l];
            }
        for (; k < n; k++)
            m4[0] = fabs(x[k]) > m4[0] ? fabs(x[k]) : m4[0];
        m4[0] = m4[1] > m4[0] ? m4[1] : m4[0];
        m4[2] = m4[3] > m4[2] ? m4[3] : m4[2];
        m = m4[2] > m4[0] ? m4[2] : m4[0];
    }
    uint64_t mbits;
    memcpy(&mbits, &m, sizeof mbits);
    const int E = (int)(mbits >> 52) - 1023; /* 2^E <= m < 2^(E+1) */
    if (m == 0.0 && fast) {
        int nan = 0;
        for (int k = 0; k < n; k++)
            nan |= x[k] != x[k];
        if (!nan)
            return 0; /* all zeros */
    }
    if (fast && E >= -900 && E <= 900) {
        const double c1 = 1.5 * pow2i(E + 1 - XW + 52), c2 = 1.5 * pow2i(E + 1 - 2 * XW + 52);
        double t1 = 0.0, t2 = 0.0;
        int rest = 0, k = 0;
#if defined(__GNUC__)
        typedef double v2d __attribute__((vector_size(16)));
        typedef int64_t v2i __attribute__((vector_size(16)));
        const v2d C1 = {c1, c1}, C2 = {c2, c2};
        v2d s1a = {0.0, 0.0}, s1b = {0.0, 0.0}, s2a = {0.0, 0.0}, s2b = {0.0, 0.0};
        v2i nz = {0, 0};
        for (; k + 4 <= n; k += 4) {
            v2d a, b;
            memcpy(&a, x + k, sizeof a);
            memcpy(&b, x + k + 2, sizeof b);
            v2d qa = (a + C1) - C1, qb = (b + C1) - C1;
            a -= qa;
            b -= qb;
            s1a += qa;
            s1b += qb;
            qa = (a + C2) - C2;
            qb = (b + C2) - C2;
            a -= qa;
            b -= qb;
            s2a += qa;
            s2b += qb;
            nz |= (a != 0.0) | (b != 0.0);
        }
        s1a += s1b; /* exact: multiples of the grid, below 2^53 of its units */
        s2a += s2b;
        t1 = s1a[0] + s1a[1];
        t2 = s2a[0] + s2a[1];
        rest = (nz[0] | nz[1]) != 0;
#endif
        for (; k < n; k++) {
            double r = x[k], q = (r + c1) - c1;
            r -= q;
            t1 += q;
            q = (r + c2) - c2;
            r -= q;
            t2 += q;
            rest |= r != 0.0;
        }
        if (t1 - t1 == 0.0 && t2 - t2 == 0.0) { /* else a NaN: value by value below */
            int64_t adds = 2;
            xacc_add(acc, t1);
            xacc_add(acc, t2);
            if (rest)
                for (k = 0; k < n; k++) {
                    double r = x[k], q = (r + c1) - c1;
                    r -= q;
                    q = (r + c2) - c2;
                    r -= q;
                    if (r != 0.0) {
                        xacc_add(acc, r);
                        adds++;
                    }
                }
            return adds;
        }
    }
    for (int k = 0; k < n; k++)
        xacc_add(acc, x[k]);
    return n;
}

/* xacc_block, then acc normalised when the xacc_add calls since the last normalisation
 * (``*adds``) leave no room for another block. */
static void xacc_flush(int64_t *acc, const double *x, int n, double m, int fast, int64_t *adds)
{
    *adds += xacc_block(acc, x, n, m, fast);
    if (*adds > XACC_SLACK - XBLOCK - 2) {
        xacc_norm(acc);
        *adds = 0;
    }
}

/* Adds n values (stride ``stride``) to the accumulator ``acc`` and normalises it. */
void parjam_exact_add(int64_t n, const double *values, int64_t stride, int64_t *acc)
{
    const int fast = xblock_fast();
    int64_t adds = 0;
    double buf[XBLOCK];
    for (int64_t k0 = 0; k0 < n; k0 += XBLOCK) {
        const int m = n - k0 < XBLOCK ? (int)(n - k0) : XBLOCK;
        double top = 0.0;
        for (int k = 0; k < m; k++) {
            const double x = values[(k0 + k) * stride], a = fabs(x);
            buf[k] = x;
            top = a > top ? a : top;
        }
        xacc_flush(acc, buf, m, top, fast, &adds);
    }
    xacc_norm(acc);
}

static int bits128(unsigned __int128 v)
{
    const uint64_t hi = (uint64_t)(v >> 64), lo = (uint64_t)v;
    if (hi)
        return 128 - __builtin_clzll(hi);
    return lo ? 64 - __builtin_clzll(lo) : 0;
}

/* The accumulated sum rounded to the nearest double, ties to even (NaN when a NaN or both
 * infinities were added, else +-inf when one was; +0.0 for an exact zero). */
double parjam_exact_value(const int64_t *acc_in)
{
    if (acc_in[XACC_NAN] || (acc_in[XACC_PINF] && acc_in[XACC_MINF]))
        return NAN;
    if (acc_in[XACC_PINF])
        return INFINITY;
    if (acc_in[XACC_MINF])
        return -INFINITY;
    int64_t a[XACC_CHUNKS];
    for (int k = 0; k < XACC_CHUNKS; k++)
        a[k] = acc_in[k];
    xacc_norm(a);
    double sign = 1.0;
    if (a[XACC_CHUNKS - 1] < 0) { /* the magnitude: negate and normalise again */
        sign = -1.0;
        for (int k = 0; k < XACC_CHUNKS; k++)
            a[k] = -a[k];
        xacc_norm(a);
    }
    int top = XACC_CHUNKS - 1;
    while (top >= 0 && a[top] == 0)
        top--;
    if (top < 0)
        return 0.0;
    /* the top three chunks (>= 65 significant bits when there are three) and a sticky bit */
    const int low = top >= 2 ? top - 2 : 0;
    unsigned __int128 v = 0;
    for (int k = top; k >= low; k--)
        v = (v << 32) | (uint64_t)a[k];
    int sticky = 0;
    for (int k = 0; k < low; k++)
        sticky |= a[k] != 0;
    int shift = bits128(v) - 53;
    if (shift < 0)
        shift = 0; /* fewer than 54 bits: exact (sticky is 0 then) */
    if (shift > 0) {
        const unsigned __int128 one = 1;
        const unsigned __int128 rem = v & ((one << shift) - 1), half = one << (shift - 1);
        v >>= shift;
        if (rem > half || (rem == half && (sticky || (v & 1))))
            v += 1;
    }
    return sign * ldexp((double)(uint64_t)v, 32 * low + shift - 1074);
}

static double powa(double x, double a)
{
    return a == 1.0 ? x : (a == 2.0 ? x * x : pow(x, a));
}

/* x_j - x_i, minimum image.  Positions are kept near [0, L), so this loops at most once or
 * twice.  Across the boundary x ~ +-L would round at ulp(L); the particle near L is shifted by
 * L first (exact for positions in [L/2, 2L]) and the small numbers are subtracted, so overlaps
 * of 1e-8 keep ~1e-16 absolute precision whatever L (parjam.net.system). */
static ALWAYS_INLINE double separation(double xi, double xj, double L)
{
    double x = xj - xi;
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
    return x;
}

/* Contact forces on the owned particles [lo, hi) of ``pos`` from the pairs into ``force``
 * (zeroed first); returns the energy of the pairs whose first particle is owned.  ``d`` and
 * ``law`` (HARMONIC: alpha = 2, HERTZ: alpha = 5/2, else any alpha by pow) are constants at the
 * call sites in forces(), which are inlined, so the harmonic loop holds no pow and no branch on
 * alpha, the Hertzian one one sqrt per contact instead of two pows (delta^(3/2) = delta
 * sqrt(delta), delta^(5/2) = delta^2 sqrt(delta): the forces of a random start at N = 16,384
 * in 1.65 ms instead of 3.94), and the loops over d unroll. */
enum { GENERAL = 0, HARMONIC = 1, HERTZ = 2 };

static ALWAYS_INLINE double pair_loop(int64_t npairs, const int64_t *pi, const int64_t *pj,
                               const double *pos, const double *diam, double L, int d,
                               double alpha, double eps, int64_t lo, int64_t hi, double *force,
                               int64_t *eacc, const int law)
{
    double energy = 0.0;
    int64_t icur = -1;
    double ecur = 0.0; /* the energy of the pairs (icur, j > icur) so far, in pair order */
    const int fast = eacc ? xblock_fast() : 0;
    double eblock[XBLOCK]; /* the lower ends' energies not yet added to eacc */
    int en = 0;
    int64_t adds = 0;
    for (int64_t k = 0; k < (hi - lo) * d; k++)
        force[k] = 0.0;
    for (int64_t p = 0; p < npairs; p++) {
        const int64_t i = pi[p], j = pj[p];
        double dr[3], r2 = 0.0;
        for (int a = 0; a < d; a++) {
            const double x = separation(pos[i * d + a], pos[j * d + a], L);
            dr[a] = x;
            r2 += x * x;
        }
        const double sigma = 0.5 * (diam[i] + diam[j]);
        if (r2 >= sigma * sigma)
            continue;
        const double r = sqrt(r2);
        const double delta = 1.0 - r / sigma;
        /* V'(r) = -(eps/sigma) delta^(alpha-1) */
        const double sd = law == HERTZ ? sqrt(delta) : 0.0;
        const double dv = -(eps / sigma) * (law == HARMONIC ? delta
                                            : law == HERTZ ? delta * sd
                                                           : powa(delta, alpha - 1.0));
        const double c = -dv / r; /* force on j = c dr */
        if (j >= lo && j < hi)
            for (int a = 0; a < d; a++)
                force[(j - lo) * d + a] += c * dr[a];
        if (i >= lo && i < hi) {
            for (int a = 0; a < d; a++)
                force[(i - lo) * d + a] -= c * dr[a];
            const double e = law == HARMONIC ? (eps / 2.0) * (delta * delta)
                             : law == HERTZ    ? (eps / alpha) * (delta * delta * sd)
                                               : (eps / alpha) * powa(delta, alpha);
            if (!eacc) {
                energy += e;
            } else {
                /* The pairs are grouped by their lower end.  Without a branch (which end a
                 * group has is not predictable): the running group's sum is written to the
                 * block's next slot at every pair, and the slot is kept (en advanced) when a
                 * new group begins; the new group's sum starts from +0. */
                const uint64_t next = i != icur;
                uint64_t eb;
                eblock[en] = ecur;
                en += (int)next;
                memcpy(&eb, &ecur, sizeof eb);
                eb &= next - 1; /* all ones: the same group; 0: a new one */
                memcpy(&ecur, &eb, sizeof eb);
                ecur += e;
                icur = i;
                if (en == XBLOCK) {
                    xacc_flush(eacc, eblock, en, -1.0, fast, &adds);
                    en = 0;
                }
            }
        }
    }
    if (eacc) {
        eblock[en++] = ecur;
        xacc_flush(eacc, eblock, en, -1.0, fast, &adds);
        xacc_norm(eacc);
    }
    return energy;
}

static double forces(int64_t npairs, const int64_t *pi, const int64_t *pj, const double *pos,
                     const double *diam, double L, int d, double alpha, double eps, int64_t lo,
                     int64_t hi, double *force, int64_t *eacc)
{
    const int law = alpha == 2.0 ? HARMONIC : alpha == 2.5 ? HERTZ : GENERAL;
#define PJ_LOOP(D, LAW) \
    return pair_loop(npairs, pi, pj, pos, diam, L, D, alpha, eps, lo, hi, force, eacc, LAW)
    if (d == 3)
        switch (law) {
        case HARMONIC: PJ_LOOP(3, HARMONIC);
        case HERTZ: PJ_LOOP(3, HERTZ);
        default: PJ_LOOP(3, GENERAL);
        }
    if (d == 2)
        switch (law) {
        case HARMONIC: PJ_LOOP(2, HARMONIC);
        case HERTZ: PJ_LOOP(2, HERTZ);
        default: PJ_LOOP(2, GENERAL);
        }
    PJ_LOOP(d, GENERAL);
#undef PJ_LOOP
}

/* ``eacc`` NULL: returns the energy summed in pair order; else the energies of the pairs with
 * an owned lower end, summed per lower end in pair order, are added to the exact accumulator
 * ``eacc`` (normalised; XACC_LEN values), and 0 is returned. */
double parjam_pair_forces(int64_t npairs, const int64_t *pi, const int64_t *pj, const double *pos,
                          const double *diam, double L, int d, double alpha, double eps,
                          int64_t lo, int64_t hi, double *force, int64_t *eacc)
{
    return forces(npairs, pi, pj, pos, diam, L, d, alpha, eps, lo, hi, force, eacc);
}

/* |x - ref|^2 of one particle (minimum image; components in order). */
static ALWAYS_INLINE double displacement2(const int d, const double *x, const double *ref,
                                          double L)
{
    double s = 0.0;
    for (int a = 0; a < d; a++) {
        double dx = x[a] - ref[a];
        if (dx > 0.5 * L || dx < -0.5 * L) /* rare: only after positions were folded */
            dx -= L * rint(dx / L);
        s += dx * dx;
    }
    return s;
}

/* FIRE's velocity/position update of rows [k0, k1) (see parjam_fire_step); with ``disp`` also
 * returns the largest displacement^2 of those rows from ``ref`` (row k's reference at
 * ref[(k - k0) d]), taken while the row is in registers, so the step needs no second pass over
 * the positions for the neighbour-list criterion. */
static ALWAYS_INLINE double update_rows(const int d, int64_t k0, int64_t k1, double *x, double *v,
                                        const double *f, const double *ref, double L, double dt,
                                        int reset, double back, double mix_v, double mix_f,
                                        const int disp)
{
    double m = 0.0;
    for (int64_t k = k0; k < k1; k++) {
        for (int a = 0; a < d; a++) {
            const int64_t q = k * d + a;
            double vk = v[q];
            if (reset) {
                x[q] += back * vk;
                vk = 0.0;
            }
            vk += dt * f[q];
            vk = mix_f * f[q] + mix_v * vk;
            v[q] = vk;
            x[q] += dt * vk;
        }
        if (disp) {
            const double s = displacement2(d, x + k * d, ref + (k - k0) * d, L);
            if (s > m)
                m = s;
        }
    }
    return m;
}

/* The update of the nown owned rows (their largest displacement^2 returned) and of the ghost
 * rows after them; ``d`` a constant at each call, so the loops over it unroll. */
static double update(int64_t nown, int64_t nall, int d, double *x, double *v, const double *f,
                     const double *ref, double L, double dt, int reset, double back,
                     double mix_v, double mix_f)
{
#define PJ_UPDATE(D)                                                                      \
    do {                                                                                  \
        const double m = update_rows(D, 0, nown, x, v, f, ref, L, dt, reset, back, mix_v, \
                                     mix_f, 1);                                          \
        update_rows(D, nown, nall, x, v, f, ref, L, dt, reset, back, mix_v, mix_f, 0);    \
        return m;                                                                         \
    } while (0)
    if (d == 3)
        PJ_UPDATE(3);
    if (d == 2)
        PJ_UPDATE(2);
    PJ_UPDATE(d);
#undef PJ_UPDATE
}

enum { FIRE_UPDATE = 1, FIRE_FORCES = 2, FIRE_ENERGY = 4 };

/* One FIRE step on the nown owned particles (x, v, f: nall x d, C order, the owned rows first;
 * the nall - nown rows after them are other ranks' particles, ghosts, updated alike).
 *
 * FIRE_UPDATE (Bitzek et al., PRL 97, 170201 (2006); semi-implicit Euler as in Guenole et al.,
 * Comput. Mater. Sci. 175, 109584 (2020)), with the scalars the caller derived from the last
 * reduction:  if ``reset`` (P <= 0): x += back v, v = 0;  then v += dt F;  v = mix_f F + mix_v v
 * (mix_v = 1 - a, mix_f = a |v|/|F|);  x += dt v, on all nall rows: a ghost row given its owner's
 * x, v and F moves exactly as the owner moves it.  The largest displacement^2 of an owned
 * particle from ``ref`` (the neighbour list's positions), taken in the same pass, goes to the
 * last entry of ``acc`` (as the bits of the non-negative double).  When stale2 > 0 and it is
 * stale2 or more, returns 1 without computing forces: the caller rebuilds the list and calls
 * again with FIRE_FORCES alone.
 *
 * FIRE_FORCES: the forces on the owned particles from the pairs over ``pos`` (the owned block is
 * [lo, hi) of pos; on one rank pos is x itself), then the step's sums over the owned particles
 * into ``acc`` (FIRE_ACC int64): exact accumulators (XACC_LEN each, normalised) of the energy
 * (with FIRE_ENERGY, else left 0: FIRE decides on the others, and the energy's sum costs 5 - 6 %
 * of a step), F.v, |F|^2 and |v|^2, each summed per particle first (its pairs, its d components, in a fixed
 * order), then the maxima of |F_i|^2 and |v_i|^2 as the bits of the non-negative doubles
 * (ordered as int64).  The last entry, the displacement^2, is left as it is: the update's, or
 * the caller's (0 when the list was just built, so ref = x).  The ranks' buffers are reduced by
 * integer sums and maxima, and ``parjam_fire_sums`` turns the result into doubles: the same bits
 * on any number of ranks. */
enum { FIRE_ACC = 4 * XACC_LEN + 3 };

static ALWAYS_INLINE int64_t max_bits(double x)
{
    int64_t b;
    memcpy(&b, &x, sizeof b);
    return b;
}

int parjam_fire_step(int mode, int64_t nown, int64_t nall, int d, double *x, double *v, double *f,
                     const double *ref, double L, double dt, int reset, double back, double mix_v,
                     double mix_f, double stale2, int64_t npairs, const int64_t *pi,
                     const int64_t *pj, const double *pos, const double *diam, double alpha,
                     double eps, int64_t lo, int64_t hi, int64_t *acc)
{
    if (mode & FIRE_UPDATE) {
        const double disp2 = update(nown, nall, d, x, v, f, ref, L, dt, reset, back, mix_v, mix_f);
        acc[FIRE_ACC - 1] = max_bits(disp2);
        if (stale2 > 0.0 && disp2 >= stale2)
            return 1;
    }
    if (mode & FIRE_FORCES) {
        for (int k = 0; k < FIRE_ACC - 1; k++) /* the displacement (last) is the update's */
            acc[k] = 0;
        int64_t *ae = acc, *ap = acc + XACC_LEN, *af = acc + 2 * XACC_LEN;
        int64_t *av = acc + 3 * XACC_LEN;
        forces(npairs, pi, pj, pos, diam, L, d, alpha, eps, lo, hi, f,
               (mode & FIRE_ENERGY) ? ae : NULL);
        double fm = 0.0, vm = 0.0, bp[XBLOCK], bf[XBLOCK], bv[XBLOCK];
        const int fast = xblock_fast();
        int64_t adds_p = 0, adds_f = 0, adds_v = 0;
        for (int64_t k0 = 0; k0 < nown; k0 += XBLOCK) { /* blocks of particles */
            const int n = nown - k0 < XBLOCK ? (int)(nown - k0) : XBLOCK;
            double pb = 0.0, fb = 0.0, vb = 0.0; /* the block's largest |F.v|, |F|^2, |v|^2 */
            for (int b = 0; b < n; b++) {
                const int64_t k = k0 + b;
                double p = 0.0, fk = 0.0, vk = 0.0;
                for (int a = 0; a < d; a++) {
                    const double fa = f[k * d + a], va = v[k * d + a];
                    p += fa * va;
                    fk += fa * fa;
                    vk += va * va;
                }
                bp[b] = p;
                bf[b] = fk;
                bv[b] = vk;
                const double ab = fabs(p);
                pb = ab > pb ? ab : pb;
                fb = fk > fb ? fk : fb;
                vb = vk > vb ? vk : vb;
            }
            xacc_flush(ap, bp, n, pb, fast, &adds_p);
            xacc_flush(af, bf, n, fb, fast, &adds_f);
            xacc_flush(av, bv, n, vb, fast, &adds_v);
            fm = fb > fm ? fb : fm;
            vm = vb > vm ? vb : vm;
        }
        xacc_norm(ap);
        xacc_norm(af);
        xacc_norm(av);
        acc[FIRE_ACC - 3] = max_bits(fm);
        acc[FIRE_ACC - 2] = max_bits(vm);
    }
    return 0;
}

/* floor(v), the same value as libm's (signed zeros included), inlined: below 2^52 in magnitude
 * the truncation by conversion, less one where it rounded up; above, v is an integer (or NaN or
 * infinite) already. */
static ALWAYS_INLINE double floor_exact(double v)
{
    if (!(fabs(v) < 0x1p52))
        return v;
    double t = (double)(int64_t)v;
    t -= t > v ? 1.0 : 0.0;
    return t == 0.0 ? copysign(0.0, v) : t;
}

/* The n rows of d coordinates ``x`` folded into the box, out = max(x - L floor(x invL), 0) with
 * invL = 1 / L as the caller rounded it (parjam.net.domain.SlabDomain.fold's arithmetic, the same
 * bits), and, with nb > 0, the owner of each row, the slab k of ``bounds`` (nb + 1 values) with
 * bounds[k] <= out[row, 0] < bounds[k + 1] (searchsorted(bounds, x, "right") - 1, clipped to
 * [0, nb - 1]: SlabDomain.owner; of x itself when out is NULL).  One pass, no temporaries (numpy's four passes over
 * fresh arrays cost 0.3 - 0.4 ms at 8,192 particles in a rebuild). */
void parjam_fold_owner(int64_t n, int d, const double *x, double L, double invL, int64_t nb,
                       const double *bounds, double *out, int64_t *owner)
{
    for (int64_t k = 0; k < n; k++) {
        if (out) /* else x is folded already: the owners alone */
            for (int a = 0; a < d; a++) {
                const double v = x[k * d + a];
                const double o = v - L * floor_exact(v * invL);
                out[k * d + a] = o > 0.0 || o != o ? o : 0.0; /* np.maximum(o, 0.0), -0 to +0 */
            }
        if (nb > 0) {
            const double x0 = out ? out[k * d] : x[k * d];
            int64_t lo = 0, hi = nb + 1; /* the first bound > x0 (NaN: past all, as numpy) */
            if (x0 != x0)
                lo = hi;
            else if (nb <= 16) { /* few slabs: count the bounds <= x0, without a branch */
                for (int64_t b = 0; b <= nb; b++)
                    lo += bounds[b] <= x0;
                hi = lo;
            }
            while (lo < hi) {
                const int64_t mid = (lo + hi) / 2;
                if (bounds[mid] <= x0)
                    lo = mid + 1;
                else
                    hi = mid;
            }
            const int64_t r = lo - 1;
            owner[k] = r < 0 ? 0 : r > nb - 1 ? nb - 1 : r;
        }
    }
}

/* Rows of w 8-byte values (doubles or int64) of two sources, merged: row k of dst is row rows[k] of
 * ``old`` when rows[k] < nold, else row rows[k] - nold of ``fresh`` (the rows a rank keeps and
 * those handed to it, merged by id after a migration: one pass, where a concatenation and a
 * take make two and a temporary). */
static ALWAYS_INLINE void merge_w(const int w, int64_t n, const int64_t *rows, int64_t nold,
                                   const int64_t *old, const int64_t *fresh, int64_t *dst)
{
    for (int64_t k = 0; k < n; k++) {
        const int64_t r = rows[k];
        const int64_t *from = r < nold ? old + r * w : fresh + (r - nold) * w;
        for (int a = 0; a < w; a++) /* a constant w: no call to memcpy per row */
            dst[k * w + a] = from[a];
    }
}

void parjam_merge_rows(int64_t n, int w, const int64_t *rows, int64_t nold, const void *old,
                       const void *fresh, void *dst)
{
    const int64_t *o = old, *f = fresh;
    int64_t *t = dst;
    switch (w) {
    case 1: merge_w(1, n, rows, nold, o, f, t); break;
    case 2: merge_w(2, n, rows, nold, o, f, t); break;
    case 3: merge_w(3, n, rows, nold, o, f, t); break;
    default: merge_w(w, n, rows, nold, o, f, t);
    }
}

/* dst[k] = src[idx[k]] for the n rows of d doubles (the engine's per-step packing of the ghosts'
 * forces and their unpacking: np.take costs ~20 us for 1,700 rows, this ~2). */
static ALWAYS_INLINE void gather_d(const int d, int64_t n, const int64_t *idx, const double *src,
                                    double *dst)
{
    for (int64_t k = 0; k < n; k++)
        for (int a = 0; a < d; a++)
            dst[k * d + a] = src[idx[k] * d + a];
}

void parjam_gather_rows(int64_t n, int d, const int64_t *idx, const double *src, double *dst)
{
    if (d == 3)
        gather_d(3, n, idx, src, dst);
    else if (d == 2)
        gather_d(2, n, idx, src, dst);
    else
        gather_d(d, n, idx, src, dst);
}

/* out = D v on m rows from nh half-edges (parjam.vib.rowproduct): row rows[e] gets
 * K_e (v[rows[e]] - vc[pos[e]]), each component summed over b = 0 .. d - 1 from 0, the rows
 * summed over their half-edges in the given order from 0 -- numpy's zeros, += and bincount,
 * operation for operation, so the fallback there gives the same bits. */
static ALWAYS_INLINE void halfedge_d(const int d, int64_t nh, int64_t m, const int64_t *rows,
                                     const int64_t *pos, const double *K, const double *v,
                                     const double *vc, double *out)
{
    for (int64_t k = 0; k < m * d; k++)
        out[k] = 0.0;
    for (int64_t e = 0; e < nh; e++) {
        const double *vi = v + rows[e] * d, *vj = vc + pos[e] * d, *Ke = K + e * d * d;
        double dv[3];
        for (int b = 0; b < d; b++)
            dv[b] = vi[b] - vj[b];
        for (int a = 0; a < d; a++) {
            double w = 0.0;
            for (int b = 0; b < d; b++)
                w += Ke[a * d + b] * dv[b];
            out[rows[e] * d + a] += w;
        }
    }
}

void parjam_halfedge_product(int64_t nh, int d, int64_t m, const int64_t *rows,
                             const int64_t *pos, const double *K, const double *v,
                             const double *vc, double *out)
{
    if (d == 3)
        halfedge_d(3, nh, m, rows, pos, K, v, vc, out);
    else
        halfedge_d(2, nh, m, rows, pos, K, v, vc, out);
}

/* A slab search's points at the current positions (the engine's search-only rebuild):
 * out[k] = pos[src[k]] + offset[k], then folded into [0, L) along axes 1 .. d - 1 as
 * parjam_fold_owner folds (axis 0 stays open: the plan placed each point's image there); and,
 * in the same call, ref = the first nref rows of pos (the new list's reference positions). */
static ALWAYS_INLINE void search_d(const int d, int64_t n, const int64_t *src, const double *pos,
                                   const double *offset, double L, double invL, double *out)
{
    for (int64_t k = 0; k < n; k++) {
        const double *p = pos + src[k] * d;
        out[k * d] = p[0] + offset[k * d];
        for (int a = 1; a < d; a++) {
            const double v = p[a] + offset[k * d + a];
            const double o = v - L * floor_exact(v * invL);
            out[k * d + a] = o > 0.0 || o != o ? o : 0.0;
        }
    }
}

void parjam_search_points(int64_t n, int d, const int64_t *src, const double *pos,
                          const double *offset, double L, double invL, double *out,
                          int64_t nref, double *ref)
{
    if (d == 3)
        search_d(3, n, src, pos, offset, L, invL, out);
    else if (d == 2)
        search_d(2, n, src, pos, offset, L, invL, out);
    else
        search_d(d, n, src, pos, offset, L, invL, out);
    if (ref)
        memcpy(ref, pos, (size_t)(nref * d) * sizeof(double));
}

/* The seven numbers of a (reduced) FIRE_ACC buffer: energy, F.v, |F|^2, |v|^2 (rounded to
 * nearest) and max |F_i|^2, max |v_i|^2, max displacement^2. */
void parjam_fire_sums(const int64_t *acc, double *out)
{
    for (int k = 0; k < 4; k++)
        out[k] = parjam_exact_value(acc + k * XACC_LEN);
    for (int k = 0; k < 3; k++)
        memcpy(out + 4 + k, acc + FIRE_ACC - 3 + k, sizeof(double));
}

#ifndef PARJAM_SRC_SHA
#define PARJAM_SRC_SHA "unknown"
#endif
/* SHA-256 of this file when it was compiled (parjam.pack.kernels checks it against the source) */
const char *parjam_src_sha = PARJAM_SRC_SHA;

/* Counting sort of n points by cell: ``order`` lists them cell by cell (ascending index within
 * a cell), cell c's range in it is start[c] .. start[c + 1] (start holds ncells + 1). */
static void bucket_by_cell(int64_t n, int64_t ncells, const int64_t *cellof, int64_t *start,
                           int64_t *order)
{
    for (int64_t c = 0; c <= ncells; c++)
        start[c] = 0;
    for (int64_t k = 0; k < n; k++)
        start[cellof[k] + 1]++;
    for (int64_t c = 0; c < ncells; c++)
        start[c + 1] += start[c];
    for (int64_t k = 0; k < n; k++)
        order[start[cellof[k]]++] = k;
    for (int64_t c = ncells; c > 0; c--)
        start[c] = start[c - 1];
    start[0] = 0;
}

/* ---- Neighbour search by cells, half stencil ----
 *
 * The points are counting-sorted into a grid of cells of edge >= cutoff (n0 along axis 0, nc
 * along the others, nc >= 3; axis 0 periodic like the others, or open: a slab whose halo is
 * unwrapped along it) and their positions copied in cell order ``sp``.  The cells are visited
 * in memory order and each is paired with itself and the half of its neighbours that come
 * first lexicographically (13 in 3D, 4 in 2D): every pair of points in the same or adjacent
 * cells is met exactly once.  The neighbours are taken a row at a time: the cells along the
 * last axis are contiguous in cell order, so the three neighbours (t, m-1 .. m+1) of a row are
 * one run of points (two or three runs where the row wraps around the periodic boundary), with
 * the periodic image shift applied per run -- 5 runs per cell in 3D (2 in 2D) instead of 14
 * (5) cells, each candidate one distance and no branch.  Out come the pairs within the cutoff
 * as cell-order indices (ta, tb), unsorted; the callers put them into the global (i, j) order
 * the force sums need (a counting sort by the lower end, then each short row by the upper
 * end).  Returns the number found, which may exceed cap (only the first cap are written: call
 * again with more room). */

/* The rows of neighbour cells of the half stencil: offsets along the axes before the last one
 * (3D: axes 0 and 1; 2D: axis 0), and the range of offsets along the last axis (the first row,
 * the cell's own, holds the cell itself -- points after a -- and the next cell). */
static const int ROWS3[5][3] = {{0, 0, 0}, {0, 1, -1}, {1, -1, -1}, {1, 0, -1}, {1, 1, -1}};
static const int ROWS2[2][3] = {{0, 0, 0}, {1, 0, -1}};

static ALWAYS_INLINE int64_t scan_run(const int d, const int per, int64_t a, int64_t b0,
                                      int64_t b1, const double *xa, const double *sp,
                                      double cut2, const double *sh, double ha, int64_t count,
                                      int64_t cap, int64_t *ta, int64_t *tb)
{
    for (int64_t b = b0; b < b1; b++) {
        double r2 = 0.0;
        for (int k = 0; k < d; k++) {
            const double x = sp[b * d + k] - xa[k];
            r2 += x * x;
        }
        if (count < cap) { /* written always, kept when in range */
            ta[count] = a;
            tb[count] = b;
        }
        if (per) { /* the pair's own reach: sigma_ab + skin (ha = d_a / 2 + skin) */
            const double c = ha + sh[b];
            count += r2 <= c * c;
        } else {
            count += r2 <= cut2;
        }
    }
    return count;
}

static ALWAYS_INLINE int64_t half_stencil(const int d, const int per, int64_t n0, int64_t nc,
                                          int open0, double L, double cutoff,
                                          const int64_t *start, const double *sp,
                                          const double *sh, double skin,
                                          const unsigned char *keep0, int64_t cap, int64_t *ta,
                                          int64_t *tb)
{
    const double cut2 = cutoff * cutoff;
    const int64_t n1 = d == 3 ? nc : 1, nl = nc; /* nl: cells along the last axis */
    const int nrows = d == 3 ? 5 : 2;
    int64_t count = 0;
    for (int64_t m0 = 0; m0 < n0; m0++)
        for (int64_t m1 = 0; m1 < n1; m1++)
            for (int64_t ml = 0; ml < nl; ml++) {
                const int64_t c = (m0 * n1 + m1) * nl + ml;
                const int64_t a0 = start[c], a1 = start[c + 1];
                if (a0 == a1)
                    continue;
                for (int s = 0; s < nrows; s++) {
                    const int *o = d == 3 ? ROWS3[s] : ROWS2[s];
                    /* the row (t0, t1) of neighbour cells and its image shift */
                    double shift[3] = {0.0, 0.0, 0.0};
                    int64_t t0 = m0 + o[0], t1 = m1 + o[1];
                    if (t0 >= n0) {
                        if (open0)
                            continue;
                        t0 -= n0;
                        shift[0] = L;
                    }
                    if (keep0 && !keep0[m0] && !keep0[t0])
                        continue; /* two layers along axis 0 with no point whose pairs count */
                    if (d == 3) {
                        if (t1 < 0) {
                            t1 += n1;
                            shift[1] = -L;
                        } else if (t1 >= n1) {
                            t1 -= n1;
                            shift[1] = L;
                        }
                    }
                    const int64_t rowc = (t0 * n1 + t1) * nl; /* cell (t0, t1, 0) */
                    /* the runs along the last axis: offsets o[2] .. +1 (own row: 0 .. +1) */
                    int64_t lo = ml + o[2], hi = ml + 1; /* inclusive, may leave [0, nl) */
                    int64_t run_b0[3], run_b1[3];
                    double run_s[3];
                    int nruns = 0;
                    if (lo < 0) { /* the wrapped cell nl - 1, image -L */
                        run_b0[nruns] = start[rowc + nl - 1];
                        run_b1[nruns] = start[rowc + nl];
                        run_s[nruns++] = -L;
                        lo = 0;
                    }
                    const int64_t top = hi < nl ? hi : nl - 1;
                    run_b0[nruns] = start[rowc + lo];
                    run_b1[nruns] = start[rowc + top + 1];
                    run_s[nruns++] = 0.0;
                    if (hi >= nl) { /* the wrapped cell 0, image +L */
                        run_b0[nruns] = start[rowc];
                        run_b1[nruns] = start[rowc + 1];
                        run_s[nruns++] = L;
                    }
                    for (int64_t a = a0; a < a1; a++) {
                        const double ha = per ? sh[a] + skin : 0.0;
                        for (int r = 0; r < nruns; r++) {
                            shift[d - 1] = run_s[r];
                            /* x_b + shift - x_a = x_b - (x_a - shift) */
                            double xa[3];
                            for (int k = 0; k < d; k++)
                                xa[k] = sp[a * d + k] - shift[k];
                            /* the own row's first run starts with the cell itself: only the
                             * points after a */
                            const int64_t b0 = s == 0 && r == 0 ? a + 1 : run_b0[r];
                            count = scan_run(d, per, a, b0, run_b1[r], xa, sp, cut2, sh, ha,
                                             count, cap, ta, tb);
                        }
                    }
                }
            }
    return count;
}

#define PJ_STENCIL_CASE(NAME, D, PER)                                                          \
    static int64_t NAME(int64_t n0, int64_t nc, int open0, double L, double cutoff,              \
                        const int64_t *start, const double *sp, const double *sh, double skin,   \
                        const unsigned char *keep0, int64_t cap, int64_t *ta, int64_t *tb)       \
    {                                                                                            \
        return half_stencil(D, PER, n0, nc, open0, L, cutoff, start, sp, sh, skin, keep0, cap,   \
                            ta, tb);                                                             \
    }
PJ_STENCIL_CASE(half_stencil_3, 3, 0)
PJ_STENCIL_CASE(half_stencil_3p, 3, 1)
PJ_STENCIL_CASE(half_stencil_2, 2, 0)
PJ_STENCIL_CASE(half_stencil_2p, 2, 1)
#undef PJ_STENCIL_CASE

/* sh NULL: every pair within ``cutoff``; else each pair (a, b) within its own reach
 * sh[a] + sh[b] + skin (sh: half the diameters, in cell order; <= cutoff). */
static int64_t half_stencil_d(int d, int64_t n0, int64_t nc, int open0, double L, double cutoff,
                              const int64_t *start, const double *sp, const double *sh,
                              double skin, const unsigned char *keep0, int64_t cap, int64_t *ta,
                              int64_t *tb)
{
    typedef int64_t (*stencil_fn)(int64_t, int64_t, int, double, double, const int64_t *,
                                  const double *, const double *, double, const unsigned char *,
                                  int64_t, int64_t *, int64_t *);
    /* one function per (d, reach) case, each holding one inlined copy of the stencil: in one
     * function the four copies cost the single cutoff's search 5 - 7 % */
    const stencil_fn fn = d == 3 ? (sh ? half_stencil_3p : half_stencil_3)
                                 : (sh ? half_stencil_2p : half_stencil_2);
    return fn(n0, nc, open0, L, cutoff, start, sp, sh, skin, keep0, cap, ta, tb);
}

/* Counting sort of the pairs (lo[p], up[p]) by row lo[p] in [0, nrows) into (pi, pj) (off:
 * nrows + 1 scratch), then each row by its upper end's key ``ukey`` (insertion sort: a row
 * holds a few pairs).  The result is in (row, ukey) order. */
static void sort_rows(int64_t npairs, int64_t nrows, const int64_t *lo, const int64_t *up,
                      const int64_t *ukey, int64_t *off, int64_t *pi, int64_t *pj)
{
    for (int64_t r = 0; r <= nrows; r++)
        off[r] = 0;
    for (int64_t p = 0; p < npairs; p++)
        off[lo[p] + 1]++;
    for (int64_t r = 0; r < nrows; r++)
        off[r + 1] += off[r];
    for (int64_t p = 0; p < npairs; p++) {
        const int64_t q = off[lo[p]]++;
        pi[q] = lo[p];
        pj[q] = up[p];
    }
    /* off[r] is now the end of row r */
    for (int64_t r = 0, first = 0; r < nrows; first = off[r], r++)
        for (int64_t p = first + 1; p < off[r]; p++) {
            const int64_t key = pj[p];
            int64_t q = p - 1;
            while (q >= first && ukey[pj[q]] > ukey[key]) {
                pj[q + 1] = pj[q];
                q--;
            }
            pj[q + 1] = key;
        }
}

/* Neighbour search of a whole periodic box by cells (cellsearch.cell_pair_lists): the pairs
 * i < j with |x_j - x_i| <= cutoff (minimum image) of the n points ``pos`` folded into [0, L),
 * each once, in (i, j) order, in (pi, pj); given the diameters ``diam`` (else NULL), only the
 * pairs within their own reach (d_i + d_j) / 2 + skin <= cutoff.  The box holds nc >= 3 cells
 * of edge >= cutoff per direction.  Scratch: start (nc^d + 1), order and cellof (n), sp (n d),
 * sh (n, with diam), off (n + 1), ta and tb (cap).  Returns the number of pairs, or -(number
 * needed) when cap is too small. */
int64_t parjam_cell_pairs(int64_t n, int d, const double *pos, double L, double cutoff, int nc,
                          const double *diam, double skin, int64_t *start, int64_t *order,
                          int64_t *cellof, double *sp, double *sh, int64_t *off, int64_t cap,
                          int64_t *ta, int64_t *tb, int64_t *pi, int64_t *pj)
{
    int64_t ncells = 1;
    for (int a = 0; a < d; a++)
        ncells *= nc;
    const double scale = nc / L;
    for (int64_t k = 0; k < n; k++) {
        int64_t c = 0;
        for (int a = 0; a < d; a++) {
            int64_t m = (int64_t)(pos[k * d + a] * scale);
            c = c * nc + (m < 0 ? 0 : (m >= nc ? nc - 1 : m));
        }
        cellof[k] = c;
    }
    bucket_by_cell(n, ncells, cellof, start, order);
    for (int64_t q = 0; q < n; q++)
        for (int a = 0; a < d; a++)
            sp[q * d + a] = pos[order[q] * d + a];
    if (diam)
        for (int64_t q = 0; q < n; q++)
            sh[q] = 0.5 * diam[order[q]];
    const int64_t count = half_stencil_d(d, nc, nc, 0, L, cutoff, start, sp, diam ? sh : NULL,
                                         skin, NULL, cap, ta, tb);
    if (count > cap)
        return -count;
    for (int64_t p = 0; p < count; p++) { /* cell order -> ids, lower end first */
        const int64_t i = order[ta[p]], j = order[tb[p]];
        ta[p] = i < j ? i : j;
        tb[p] = i < j ? j : i;
    }
    for (int64_t k = 0; k < n; k++)
        order[k] = k; /* the upper end's key: its id */
    sort_rows(count, n, ta, tb, order, off, pi, pj);
    return count;
}

/* The search of a slab too thin for the half stencil (fewer than 3 cells across a periodic
 * direction, a small box): for each lower end in ``low`` order every cell of the neighbouring
 * x layers, with the minimum image per candidate along the periodic directions; each row
 * sorted by the upper end's global id. */
static int64_t slab_narrow(int d, const double *pos, double L, double cutoff, int64_t nx,
                           int64_t nc, const double *diam, double skin, const double *sh,
                           const int64_t *row, const int64_t *gid, const int64_t *kind,
                           int64_t nlow, const int64_t *low, const int64_t *start,
                           const int64_t *order, const int64_t *cellof, const double *sp,
                           const int64_t *sg, int64_t cap, int64_t *pi, int64_t *pj)
{
    const double cut2 = cutoff * cutoff;
    int64_t cells_x = 1; /* cells per x layer */
    for (int a = 1; a < d; a++)
        cells_x *= nc;
    int64_t count = 0;
    for (int64_t t = 0; t < nlow; t++) {
        const int64_t i = low[t];
        const int64_t first = count;
        /* j is kept when gid[j] > gid[i] and (i or j owned): with g = 2 gid + (not owned),
         * g_j >= gi2 + 2 (gid[i] owned) or g_j = 2 gid[j] >= gi2 + 1 with j owned */
        const int64_t gi2 = 2 * gid[i];
        const int own_i = kind[i] == 0;
        const int64_t m0 = cellof[i] / cells_x;
        for (int64_t t0 = m0 - 1; t0 <= m0 + 1; t0++) {
            if (t0 < 0 || t0 >= nx)
                continue;
            for (int64_t q = start[t0 * cells_x]; q < start[(t0 + 1) * cells_x]; q++) {
                const int64_t g = sg[q];
                if (own_i ? g < gi2 + 2 : (g & 1) || g <= gi2)
                    continue;
                double r2 = 0.0;
                for (int a = 0; a < d; a++) {
                    double x = sp[q * d + a] - pos[i * d + a];
                    if (a > 0 && (x > 0.5 * L || x < -0.5 * L))
                        x -= L * rint(x / L);
                    r2 += x * x;
                }
                if (diam) {
                    const double c = 0.5 * diam[i] + skin + sh[q];
                    if (r2 > c * c)
                        continue;
                } else if (r2 > cut2) {
                    continue;
                }
                if (count < cap) {
                    pi[count] = i;
                    pj[count] = q; /* a cell-order index until the row is sorted */
                }
                count++;
            }
        }
        if (count <= cap) {
            /* the group of i by the upper end's global id (insertion sort of a few entries) */
            for (int64_t p = first + 1; p < count; p++) {
                const int64_t key = pj[p];
                int64_t q = p - 1;
                while (q >= first && sg[pj[q]] > sg[key]) {
                    pj[q + 1] = pj[q];
                    q--;
                }
                pj[q + 1] = key;
            }
            for (int64_t p = first; p < count; p++) {
                pi[p] = row[pi[p]];
                pj[p] = row[order[pj[p]]];
            }
        }
    }
    return count <= cap ? count : -count;
}

/* Neighbour search of one slab (cellsearch.slab_pairs, parjam.pack.engine): n search points -- a rank's
 * owned particles (kind 0), images of its own particles across the periodic boundary (kind 1)
 * and ghosts of other ranks (kind 2) -- open along axis 0 (the halo is unwrapped there) and
 * periodic with edge L along the others.  A pair of points closer than ``cutoff`` is kept when
 * one end is an owned particle and the other has a larger global id ``gid``; a pair whose upper
 * end is an own image is kept only from an owned lower end (each physical pair once).  The pairs
 * come out as rows ``row[a]`` < ... of the force arrays, grouped by their lower end in the order
 * ``low`` (kinds 0 and 2 by global id) and, within a group, by the upper end's global id: the
 * global (i, j) order, so the contact forces on a particle are summed in the same order on any
 * number of ranks.  Cells: nx of edge w0 along axis 0 from x0min, nc of edge L / nc along the
 * others: the half stencil when nc >= 3, else ``slab_narrow``.  Given the points' diameters
 * ``diam`` (else NULL) only the pairs within their own reach (d_a + d_b) / 2 + skin <= cutoff
 * are kept.  Scratch: start (ncells + 1), order, cellof, sg, place (n), sp (n d), sh (n, with
 * diam), off (nlow + 1), ta and tb (cap).
 * Returns the number of pairs, or -(number needed) when cap is too small. */
int64_t parjam_slab_pairs(int64_t n, int d, const double *pos, double L, double cutoff,
                          double x0min, double w0, int64_t nx, int64_t nc, const double *diam,
                          double skin, const int64_t *row, const int64_t *gid,
                          const int64_t *kind, int64_t nlow, const int64_t *low, int64_t *start,
                          int64_t *order, int64_t *cellof, double *sp, double *sh, int64_t *sg,
                          int64_t *place, int64_t *off, int64_t cap, int64_t *ta, int64_t *tb,
                          int64_t *pi, int64_t *pj)
{
    int64_t ncells = nx;
    for (int a = 1; a < d; a++)
        ncells *= nc;
    const double scale = nc / L;
    for (int64_t k = 0; k < n; k++) {
        int64_t m = (int64_t)((pos[k * d] - x0min) / w0);
        int64_t c = m < 0 ? 0 : (m >= nx ? nx - 1 : m);
        for (int a = 1; a < d; a++) {
            m = (int64_t)(pos[k * d + a] * scale);
            c = c * nc + (m < 0 ? 0 : (m >= nc ? nc - 1 : m));
        }
        cellof[k] = c;
    }
    bucket_by_cell(n, ncells, cellof, start, order);
    /* positions, and the global id (times 2, plus 1 for a non-owned point), in cell order, so
     * that a cell's candidates are read contiguously */
    for (int64_t q = 0; q < n; q++) {
        const int64_t k = order[q];
        for (int a = 0; a < d; a++)
            sp[q * d + a] = pos[k * d + a];
        sg[q] = 2 * gid[k] + (kind[k] != 0);
        if (diam)
            sh[q] = 0.5 * diam[k];
    }
    if (nc < 3)
        return slab_narrow(d, pos, L, cutoff, nx, nc, diam, skin, sh, row, gid, kind, nlow, low,
                           start, order, cellof, sp, sg, cap, pi, pj);
    /* a layer of cells along axis 0 with no owned point pairs only with the next layer's owned
     * points: the search skips the pairs of two such layers (the halo's ghosts among
     * themselves, when the caller aligns the layers with the slab: cellsearch.slab_pairs) */
    int64_t cells_x = 1;
    for (int a = 1; a < d; a++)
        cells_x *= nc;
    unsigned char *keep0 = malloc((size_t)nx);
    if (keep0) {
        memset(keep0, 0, (size_t)nx);
        for (int64_t k = 0; k < n; k++)
            if (kind[k] == 0)
                keep0[cellof[k] / cells_x] = 1;
    }
    const int64_t found = half_stencil_d(d, nx, nc, 1, L, cutoff, start, sp, diam ? sh : NULL,
                                         skin, keep0, cap, ta, tb);
    free(keep0);
    if (found > cap)
        return -found;
    for (int64_t k = 0; k < n; k++)
        place[k] = -1;
    for (int64_t t = 0; t < nlow; t++)
        place[low[t]] = t;
    int64_t count = 0;
    for (int64_t p = 0; p < found; p++) {
        int64_t a = order[ta[p]], b = order[tb[p]];
        if (gid[a] == gid[b])
            continue; /* a particle and its own image */
        if (gid[a] > gid[b]) {
            const int64_t s = a;
            a = b;
            b = s;
        }
        if (place[a] < 0 || !(kind[a] == 0 || (kind[a] == 2 && kind[b] == 0)))
            continue; /* no owned end, or an own image as the lower end */
        ta[count] = place[a];
        tb[count] = b;
        count++;
    }
    sort_rows(count, nlow, ta, tb, gid, off, pi, pj);
    for (int64_t p = 0; p < count; p++) {
        pi[p] = row[low[pi[p]]];
        pj[p] = row[pj[p]];
    }
    return count;
}
