"""Energy minimisation to force balance: FIRE to a loose tolerance, then Newton steps with the
exact Hessian (parjam.pack.newtonsolve: a MUMPS factorisation, or exact-sum conjugate gradients
for large systems) down to the round-off floor.  For large
systems (more than FIRE_TAIL_DOF degrees of freedom) FIRE goes on to the tolerance itself and
Newton is only the fall-back when FIRE does not get there: a Newton step then costs thousands of
FIRE steps.

FIRE: parjam.pack.fire (Bitzek et al., PRL 97, 170201 (2006); FIRE 2.0 of Guenole et al., Comput.
Mater. Sci. 175, 109584 (2020), as an option); its names are re-exported here.  Newton:
Levenberg-Marquardt shift mu ~ max|F| so that near-zero modes are damped while the residual is
large, the d global translations projected out of the right-hand side and of the step, and a
backtracking line search on the energy.

Every number a decision here rests on is the same bits on any number of ranks: FIRE's (parjam.pack.fire),
the energy and max |F| of a force evaluation (parjam.pack.forces), the translations removed
(exact means) and Newton's steps (parjam.pack.newtonsolve's solvers).  So a minimisation ends in
the same positions, bitwise, on 1 or P ranks.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net import exactsum, potential
from parjam.pack import fire as fire_mod
from parjam.pack import newtonsolve
from parjam.pack.fire import SNAPSHOT_EVERY, FireParams, FireState, MinResult, fire  # noqa: F401
from parjam.pack.newtonsolve import NEWTON_CG_DOF, remove_translations  # noqa: F401


def factor_shifted(ff, mu):
    """Factorise H + mu I with the rank-independent solver kept on ff (parjam.pack.newtonsolve:
    a MUMPS LDL^T on the first rank up to NEWTON_CG_DOF, else exact-sum CG); returns its number
    of negative pivots (None: unknown, CG), the same on every rank (collective)."""
    if ff.newton_ksp is None:
        ff.newton_ksp = newtonsolve.solver_for(ff)
    return ff.newton_ksp.factor(ff, mu)


def _newton_shift(fmax):
    """Levenberg-Marquardt shift ~ max|F|; the floor keeps rattler zero modes bounded."""
    return min(1e-2, max(fmax, 1e-10))


def newton(ff, ftol, max_steps=60, progress=None):
    """Damped Newton iterations from ff.x until max|F| <= ftol."""
    ff.renew_neighbours()
    f = ff.vec()
    f_trial = ff.vec()
    dx = ff.vec()
    x0 = ff.vec()
    energy = ff.evaluate(f)
    fmax = ff.max_norm(f)
    status = "not converged"
    step = 0
    mu_scale = 1.0
    tight = 0.1 * ftol  # aim below the tolerance; stop at ftol only when progress stalls
    for step in range(1, max_steps + 1):
        if fmax <= tight:
            status = "converged"
            break
        mu = mu_scale * _newton_shift(fmax)
        if factor_shifted(ff, mu):
            # H + mu I is indefinite: not yet in the basin of a minimum (a saddle region, the
            # contact network still rearranging), where Newton steps wander; FIRE goes on
            status = "saddle"
            break
        remove_translations(ff, f)
        if ff.newton_ksp.solve(ff, f, dx) < 0:
            # an iterative solve (exact CG above NEWTON_CG_DOF, or -newton_ksp_type cg) met
            # negative curvature or did not converge: the same gate as the inertia of a
            # factorisation
            status = "saddle"
            break
        remove_translations(ff, dx)
        ff.x.copy(x0)
        accepted = False
        s = 1.0
        for _ in range(12):
            x0.copy(ff.x)
            ff.x.axpy(s, dx)
            ff.wrap()
            e_new = ff.evaluate(f_trial)
            fmax_new = ff.max_norm(f_trial)
            # within round-off of the energy its comparison is noise: judge by the force
            flat = abs(e_new - energy) <= 1e-13 * abs(energy) + 1e-300
            if (e_new < energy and not flat) or (flat and fmax_new < fmax):
                accepted = True
                break
            s *= 0.5
        if not accepted:
            x0.copy(ff.x)
            ff.wrap()
            mu_scale *= 100.0
            if mu_scale > 1e12 or fmax <= ftol:  # below ftol already: one failure is the floor
                break
            continue
        mu_scale = max(1.0, mu_scale / 10.0)
        f_trial.copy(f)
        stalled = fmax_new <= ftol and fmax_new > 0.5 * fmax  # at the round-off floor
        energy, fmax = e_new, fmax_new
        if stalled:
            break
        if progress is not None:
            progress(f"Newton step {step}: E/N = {energy / ff.n:.3e}, max|F| = {fmax:.3e}")
    if fmax <= ftol:
        status = "converged"
    ff.evaluate(f)
    for vec in (f, f_trial, dx, x0):
        vec.destroy()
    return MinResult(status, energy, fmax, newton_steps=step)


@dataclass
class MinimiseState:
    """Where an interrupted ``minimise`` stands: in the FIRE run of round ``round`` (0: the
    first FIRE; k >= 1: the FIRE after the k-th Newton attempt), with that run's tolerance,
    the steps of the rounds before it, and FIRE's own state."""

    round: int
    tol: float
    fire_rel: float
    fire_steps: int
    newton_steps: int
    fire: FireState


# Above this many degrees of freedom FIRE itself converges to ftol; Newton is only the fall-back
# when FIRE does not (its step cap).  Measured with scripts/pack_steps.py (the extrapolation
# protocol to dphi = 1e-3, 3D, 1 rank, same seeds, one other job on the second core; docs/explanation/scaling.md), time of FIRE + Newton against FIRE alone: N = 1024 12.4 s / 11.3 s (4 seeds),
# 4096 95 / 56 s (3), 8192 558 / 290 s (4), 16384 1446 / 989 s (3), 32768 3765 / 1329 s (1, where
# Newton's CG + GAMG steps took 77 % of the run); at dphi = 1e-6, N = 4096 (2 seeds) 247 / 211 s.
# FIRE alone needs more FIRE steps (up to 1.5x), but a Newton step costs ~10^3 (MUMPS) to 10^4
# (CG + GAMG) of them.  In 2D (bidisperse, 2 seeds each) FIRE + Newton against FIRE
# alone: N = 4096 23.6 / 28.5 s, 8192 55.5 / 46.7 s, 16384 576 / 396 s, and 4096 at
# dphi = 1e-6 168 / 98 s: the 2D factorisation is cheap, so the Newton tail still pays at the
# threshold, but not above it or near jamming; one threshold serves both dimensions.
# Below this size the Newton tail is as cheap and keeps the tests' small packings on it.
FIRE_TAIL_DOF = 6000


def minimize(ff, ftol=1e-13, e_stop=-np.inf, fire_rel=1e-4, progress=None, fire_params=None,
             attempts=8, snapshot=None, resume=None):
    """FIRE until max|F| < fire_rel * (mean contact force), then Newton to ftol; above
    FIRE_TAIL_DOF degrees of freedom FIRE until max|F| < ftol (fire_rel = 0).

    Returns "unjammed" as soon as the energy drops below ``e_stop`` (useful in the phi_c
    bisection: the energy only decreases during minimisation).  Newton starts only where the
    Hessian is positive definite (the basin of a minimum): in a saddle region, or where Newton
    stalls (a contact network still rearranging, near jamming), FIRE goes on to a tolerance ten
    times tighter and Newton is tried again (``attempts`` rounds).

    ``snapshot(make_state)``, if given, is offered every few FIRE steps; ``make_state()``
    (collective) returns a MinimiseState, from which ``resume`` continues an interrupted call
    with the same FIRE trajectory (parjam.files.checkpoint).
    """
    params = fire_params or fire_mod.params_for()
    total = MinResult("not converged", np.nan, np.nan)
    if ff.n * ff.d > FIRE_TAIL_DOF:
        fire_rel = 0.0
    first, start = 0, None
    if resume is not None:
        first, fire_rel, start = resume.round, resume.fire_rel, resume.fire
        total.fire_steps, total.newton_steps = resume.fire_steps, resume.newton_steps
    for rnd in range(first, attempts + 1):
        if start is not None:
            tol = resume.tol
        elif rnd == 0:
            # FIRE alone (fire_rel = 0, large systems) needs no force scale: no gather for it
            tol = max(ftol, fire_rel * _force_scale(ff)) if fire_rel > 0 else ftol
        else:
            nres = newton(ff, ftol, progress=progress)
            total.newton_steps += nres.newton_steps
            total.energy, total.fmax, total.status = nres.energy, nres.fmax, nres.status
            if nres.ok or nres.energy < e_stop:
                total.status = "unjammed" if nres.energy < e_stop else "converged"
                return total
            fire_rel *= 0.1
            # FIRE alone (fire_rel = 0) aims at ftol itself: below it lies the round-off floor
            tol = max(0.1 * ftol, fire_rel * _force_scale(ff)) if fire_rel > 0 else ftol
        hook = None
        if snapshot is not None:
            before = (rnd, tol, fire_rel, total.fire_steps, total.newton_steps)

            def hook(make_fire_state, before=before):
                snapshot(lambda: MinimiseState(*before, make_fire_state()))

        res = fire(ff, tol, e_stop, params, progress, start=start, snapshot=hook)
        start = None
        total.fire_steps += res.fire_steps
        total.energy, total.fmax, total.status = res.energy, res.fmax, res.status
        if res.status == "unjammed" or res.fmax <= ftol:
            total.status = "unjammed" if res.status == "unjammed" else "converged"
            return total
    total.status = "not converged"
    return total


def _force_scale(ff):
    """Mean contact force magnitude |V'(r)| over all contacts (0 if there are none)."""
    i, j, rij, r, sigma = ff.contacts()
    own = (i >= ff.lo) & (i < ff.hi)
    tot = exactsum.fsum(ff.mpi, np.abs(potential.dV(r[own], sigma[own], ff.alpha, ff.eps)))
    cnt = ff.mpi.allreduce(int(own.sum()))
    return tot / cnt if cnt else 0.0
